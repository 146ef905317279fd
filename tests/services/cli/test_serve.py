import enum
import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import UnionType
from typing import get_args

import click
import httpx
import pytest
from click.testing import CliRunner

from services.settings import Durability, load_settings
from tests.services.ingest.live_server import LiveServer
from tests.subprocess_server import ServerProcess, answers_http, free_port

FLEET = str(Path(sys.executable).with_name("fleet"))


@pytest.mark.slow  # starts fleet serve
def test_serve_answers_health_on_the_configured_address(tmp_path):
    port = free_port()
    env = {**os.environ, "FLEET_DATA_DIR": str(tmp_path / "data")}
    server = ServerProcess(
        [FLEET, "serve", "--http-addr", f"127.0.0.1:{port}", "--grpc-addr", f"127.0.0.1:{free_port()}"],
        env=env,  # never the machine's 51234
        log=tmp_path / "serve.out",
        errors_log=tmp_path / "serve.err",
        name="fleet serve",
        ready=answers_http(f"http://127.0.0.1:{port}/healthz"),
    )
    try:
        server.start(timeout=30)
        response = httpx.get(f"http://127.0.0.1:{port}/healthz")
        assert response.status_code == 200
        assert response.json()["status"] == "ok"
        assert httpx.get(f"http://127.0.0.1:{port}/openapi.json").status_code == 200
        assert (tmp_path / "data" / "catalog.duckdb").is_file()
    finally:
        server.stop(grace=10)
    assert "created the embedded catalog" in server.log.read_text()  # on its output, said once, on first start


@pytest.mark.slow
def test_serve_refuses_a_postgres_catalog_that_is_behind(empty_postgres_url: str, tmp_path):
    result = subprocess.run(
        [
            *(FLEET, "serve", "--data-dir", str(tmp_path), "--catalog-url", empty_postgres_url, "--auth", "on"),
            *("--http-addr", f"127.0.0.1:{free_port()}", "--grpc-addr", f"127.0.0.1:{free_port()}"),
        ],  # ports of its own: the ports are claimed before the catalog is looked at
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "fleet db upgrade" in lines[0], result.stderr


def test_serve_help_documents_every_setting():
    out = subprocess.run([FLEET, "serve", "--help"], capture_output=True, text=True, check=True).stdout
    from services.settings import Settings

    assert "FLEET_CONFIG" in out
    for name in Settings.model_fields:  # the depot's settings, none of the agent's
        assert f"FLEET_{name.upper()}" in out, name


def _scalar(annotation: object) -> bool:
    """str, int, float, bool, a path or an enum (or one of them or None)."""
    kinds = (
        [a for a in get_args(annotation) if a is not type(None)] if isinstance(annotation, UnionType) else [annotation]
    )
    return (
        len(kinds) == 1
        and isinstance(kinds[0], type)
        and issubclass(kinds[0], str | int | float | bool | Path | enum.Enum)
    )


def _shown(default: object) -> str:
    if isinstance(default, list):
        return ", ".join(default)
    if isinstance(default, bool):
        return "on" if default else "off"
    return str(default.value if isinstance(default, enum.Enum) else default)


def test_every_scalar_setting_is_an_option_described_by_its_field():
    """The options are made from Settings: one description and one default, in one place."""
    from services.cli.serve import NOT_OPTIONS, serve
    from services.settings import Settings

    options = {p.name: p for p in serve.get_params(click.Context(serve)) if isinstance(p, click.Option)}
    scalars = {n for n, field in Settings.model_fields.items() if _scalar(field.annotation)}
    assert len(scalars) > 30 and not set(NOT_OPTIONS) & scalars
    help_option = serve.get_help_option(click.Context(serve))
    made = {n for n, p in options.items() if p is not help_option}
    assert not made - set(Settings.model_fields), "fleet serve has only the depot's options"
    help_text = " ".join(
        CliRunner().invoke(serve, ["--help"], terminal_width=10_000, max_content_width=10_000).output.split()
    )  # unwrapped
    for name in [*sorted(scalars - set(NOT_OPTIONS)), "secret_fields"]:  # a list read from one string
        field, option = Settings.model_fields[name], options.get(name)
        assert option is not None, f"Settings.{name} has no fleet serve option"
        assert option.opts == ["--" + name.replace("_", "-")], option.opts
        assert option.help is not None and option.help.startswith(f"FLEET_{name.upper()}: {field.description}")
        default = field.get_default(call_default_factory=True)
        if default not in ("", None):
            assert option.help.endswith(f" [default: {_shown(default)}]"), option.help
        assert option.default is None, "a flag's default would override the environment and the TOML file"
        assert f"{option.opts[0]} " in help_text and " ".join(option.help.split()) in help_text
    for name in NOT_OPTIONS:  # named after the options, with their description
        assert f"FLEET_{name.upper()} {' '.join(str(Settings.model_fields[name].description).split())}" in help_text


def test_an_option_left_out_leaves_the_setting_to_the_environment():
    from services.cli.serve import serve

    given = serve.make_context(
        "serve",
        [
            "--max-streams",
            "5",
            "--durability",
            "off",
            "--no-scheduler",
            "--data-dir",
            "d",
            "--secret-fields",
            "vin, pin",
        ],
    ).params
    assert {k: v for k, v in given.items() if v is not None} == {
        "max_streams": 5,
        "durability": "off",
        "scheduler": False,
        "data_dir": Path("d"),
        "secret_fields": "vin, pin",
    }
    settings = load_settings(**given)
    assert (settings.max_streams, settings.durability, settings.scheduler) == (5, Durability.OFF, False)
    assert settings.secret_fields == ["vin", "pin"]


@pytest.mark.slow
def test_bad_address_is_one_clear_error(tmp_path):
    result = subprocess.run(
        [FLEET, "serve", "--data-dir", str(tmp_path), "--http-addr", "nonsense"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode != 0
    assert "HOST:PORT" in result.stderr
    assert "Traceback" not in result.stderr


# --- a second `fleet serve` is refused in one line (issue 10 points 23, 24) -------------------------


def _second_serve(
    data_dir: Path, http_port: int, grpc_port: int, *args: str, timeout: float = 60
) -> subprocess.CompletedProcess[str]:
    """`fleet serve` expected to refuse to start: it must exit by itself (a start that succeeds
    would serve until the timeout, which fails the test)."""
    env = {**os.environ, "FLEET_DATA_DIR": str(data_dir)}
    return subprocess.run(
        [FLEET, "serve", "--http-addr", f"127.0.0.1:{http_port}", "--grpc-addr", f"127.0.0.1:{grpc_port}", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _one_line(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """The first `fleet serve`, shared: each test's second serve is refused and leaves it running."""
    live = LiveServer(tmp_path_factory.mktemp("serve") / "first").start()
    yield live
    live.stop()


@pytest.mark.slow
def test_a_second_serve_on_the_grpc_port_is_refused(running: LiveServer, tmp_path: Path):
    result = _second_serve(tmp_path / "second", free_port(), running.grpc_port)
    line = _one_line(result)
    assert f"127.0.0.1:{running.grpc_port}" in line and "already in use" in line
    assert "--grpc-addr" in line and "FLEET_GRPC_ADDR" in line
    assert httpx.get(f"{running.url}/healthz").status_code == 200


@pytest.mark.slow
def test_a_second_serve_on_the_grpc_wildcard_is_refused(running: LiveServer, tmp_path: Path):
    result = _second_serve(
        tmp_path / "second",
        free_port(),
        running.grpc_port,
        "--grpc-addr",
        f"0.0.0.0:{running.grpc_port}",
        "--insecure",  # auth is off in tests: a public address needs it, and the port is what is tested
    )
    assert f"0.0.0.0:{running.grpc_port}" in _one_line(result)


@pytest.mark.slow
def test_a_second_serve_on_the_http_port_is_refused(running: LiveServer, tmp_path: Path):
    result = _second_serve(tmp_path / "second", running.http_port, free_port())
    line = _one_line(result)
    assert f"127.0.0.1:{running.http_port}" in line and "already in use" in line
    assert "--http-addr" in line and "FLEET_HTTP_ADDR" in line


@pytest.mark.slow
def test_a_second_serve_on_the_same_data_dir_names_the_first(running: LiveServer):
    assert running.proc is not None
    line = _one_line(_second_serve(running.data_dir, free_port(), free_port()))
    assert f"PID {running.proc.pid}" in line and "data dir" in line and "--data-dir" in line


@pytest.mark.slow
def test_db_commands_while_serving_name_the_holder(running: LiveServer):
    """The embedded catalog is one process's at a time: `fleet db` says which one holds it."""
    assert running.proc is not None
    url = f"duckdb:///{running.data_dir / 'catalog.duckdb'}"
    for command in ("current", "upgrade"):
        result = subprocess.run(
            [FLEET, "db", command, "--catalog-url", url], capture_output=True, text=True, timeout=60
        )
        line = _one_line(result)
        assert f"PID {running.proc.pid}" in line and "fleet serve" in line and "stop it" in line


@pytest.mark.slow
def test_a_serve_on_another_data_dir_but_the_same_embedded_catalog_is_refused(running: LiveServer, tmp_path: Path):
    assert running.proc is not None
    url = f"duckdb:///{running.data_dir / 'catalog.duckdb'}"
    line = _one_line(_second_serve(tmp_path / "second", free_port(), free_port(), "--catalog-url", url))
    assert f"PID {running.proc.pid}" in line and "embedded catalog" in line


@pytest.mark.slow
@pytest.mark.postgres
def test_two_serves_never_share_a_data_dir_even_with_postgres(empty_postgres_url: str, tmp_path: Path):
    subprocess.run(
        [FLEET, "db", "upgrade", "--catalog-url", empty_postgres_url], check=True, capture_output=True, timeout=60
    )
    first = LiveServer(tmp_path / "data", catalog_url=empty_postgres_url).start()
    try:
        assert first.proc is not None
        line = _one_line(_second_serve(first.data_dir, free_port(), free_port(), "--catalog-url", empty_postgres_url))
        assert f"PID {first.proc.pid}" in line and "--data-dir" in line
    finally:
        first.stop()


@pytest.mark.slow  # starts fleet serve
@pytest.mark.parametrize("busy", ["http", "grpc"])
def test_a_busy_port_is_refused_before_anything_is_printed_or_created(tmp_path: Path, busy: str):
    """Ports first: one line naming the port and its flag, no start-up lines, no catalog made in a
    new data dir (it used to print three start-up lines and create catalog.duckdb first)."""
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        http_port, grpc_port = (port, free_port()) if busy == "http" else (free_port(), port)
        result = _second_serve(tmp_path / "new", http_port, grpc_port)
    line = _one_line(result)
    assert f"127.0.0.1:{port}" in line and "already in use" in line and f"--{busy}-addr" in line
    assert result.stdout == ""
    assert not (tmp_path / "new" / "catalog.duckdb").exists()
    assert not (tmp_path / "new").exists() or [p.name for p in (tmp_path / "new").iterdir()] == []
