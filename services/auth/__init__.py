"""Who may do what: the depot's tokens (JWTs it signs), their scopes, signed download links, and
the checks every surface (REST, gRPC, an SDK stream's fleet property) makes with them."""
