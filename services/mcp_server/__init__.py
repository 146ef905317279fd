"""The depot for AI assistants: a Model Context Protocol server (the official `mcp` SDK) over the
REST API, acting with the caller's token. `tools.py` (the tools and resources), `depot.py` (the
caller's REST API, answers bounded), `http.py` (`/mcp` on the depot: streamable HTTP, bearer token),
`stdio.py` (`fleet mcp`, for a desktop assistant). See docs/mcp.md."""
