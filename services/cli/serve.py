"""`fleet serve`: run the service on the configured addresses."""

from __future__ import annotations

from pathlib import Path

import click


def _split_addr(addr: str) -> tuple[str, int]:
    host, _, port = addr.rpartition(":")
    if not host or not port.isdigit():
        raise click.BadParameter(f"{addr!r} is not HOST:PORT (for example 0.0.0.0:8080)")
    return host.strip("[]"), int(port)


@click.command()
@click.option("--data-dir", type=click.Path(path_type=Path), help="FLEET_DATA_DIR: hot tier and embedded "
              "defaults live here [default: ./fleet-data]")
@click.option("--http-addr", help="FLEET_HTTP_ADDR: REST API address [default: 0.0.0.0:8080]")
@click.option("--grpc-addr", help="FLEET_GRPC_ADDR: Rerun message proxy address [default: 0.0.0.0:9876]")
@click.option("--catalog-url", help="FLEET_CATALOG_URL: duckdb:///PATH or postgresql+psycopg://...")
@click.option("--warm-url", help="FLEET_WARM_URL: file:///PATH or s3://bucket/prefix")
@click.option("--cold-url", help="FLEET_COLD_URL: file:///PATH or s3://bucket/prefix")
@click.option("--s3-endpoint-url", help="FLEET_S3_ENDPOINT_URL: S3-compatible endpoint")
@click.option("--max-message-size", type=int, help="FLEET_MAX_MESSAGE_SIZE: largest message in bytes")
def serve(**flags: object) -> None:
    """Run the service. Every flag can also be set as the FLEET_* variable named in its help,
    or in a TOML file named by FLEET_CONFIG."""
    import uvicorn  # imported here: other commands start faster without the server stack

    from catalog.db import create_engine, prepare_for_service
    from services.api.app import create_app
    from services.settings import load_settings

    settings = load_settings(**flags)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    engine = create_engine(settings.catalog_url)
    done = prepare_for_service(engine)  # a catalog that is behind: one line naming `fleet db upgrade`
    if done:
        click.echo(f"fleet: {done}")
    host, port = _split_addr(settings.http_addr)
    click.echo(f"fleet: data in {settings.data_dir.resolve()}, REST on http://{settings.http_addr}")
    uvicorn.run(create_app(settings), host=host, port=port, log_level="info")
