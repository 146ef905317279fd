"""`fleet mcp`: the depot as a Model Context Protocol server over stdio, for an AI assistant."""

from __future__ import annotations

import os

import click

from services.cli.client import api_option, resolve_token


@click.command()
@api_option
def mcp(api_url: str) -> None:
    """Serve the depot's MCP tools on stdin/stdout (an assistant starts this command; docs/mcp.md).

    Tools act with the token the CLI would send (FLEET_TOKEN, else the data dir's admin token on the
    depot's machine) and nothing more: a read token's assistant cannot tag or annotate."""
    import anyio

    from services.mcp_server.stdio import serve_stdio

    anyio.run(serve_stdio, api_url, resolve_token(api_url, os.environ).token)
