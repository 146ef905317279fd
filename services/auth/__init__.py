"""Who may do what: the depot's tokens (JWTs it signs), their scopes, signed download links, and
the checks every surface (REST, gRPC, an SDK stream's fleet property) makes with them."""

# Written by `fleet serve` at first start, read by CLI commands beside it: named here, where
# importing it costs nothing (no SQLAlchemy, no JWT library).
ADMIN_TOKEN_FILE = "admin.token"
