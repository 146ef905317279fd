"""`fleet agent`: its options are made from its own settings, the `agent_*` ones (and the few it
shares with the depot's ingest), named without the prefix; one agent per spool and per port, a second refused in
one line naming who holds what and the setting to change."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from core.errors import ConflictError, InvalidArgumentError
from services.agent.settings import AgentSettings, load_agent_settings
from services.cli.agent import NOT_OPTIONS, agent
from services.cli.serve import serve
from services.settings import Settings, SharedSettings
from tests.services.cli.test_serve import _scalar
from tests.subprocess_server import ServerProcess, free_port

FLEET = str(Path(sys.executable).with_name("fleet"))


def _options(command: click.Command) -> dict[str, click.Option]:
    ctx = click.Context(command)
    help_option = command.get_help_option(ctx)
    return {
        p.name: p for p in command.get_params(ctx) if isinstance(p, click.Option) and p.name and p is not help_option
    }


def _help(command: click.Command, *args: str) -> str:
    result = CliRunner().invoke(command, [*args, "--help"], terminal_width=10_000, max_content_width=10_000)
    assert result.exit_code == 0, result.output
    return " ".join(result.output.split())  # unwrapped


def test_every_agent_setting_is_an_option_without_the_prefix():
    options = _options(agent)
    fields = AgentSettings.model_fields
    agent_scalars = {n for n, f in fields.items() if n.startswith("agent_") and _scalar(f.annotation)}
    assert {"agent_spool", "agent_listen", "agent_depot", "agent_retain_hours", "agent_durability"} <= agent_scalars
    lists = {"agent_live_include", "agent_live_exclude", "agent_watch"}  # read from one string, as --secret-fields
    help_text = _help(agent)
    for name in sorted(agent_scalars | lists | {"agent_token"}):
        field, option = fields[name], options.get(name)
        assert option is not None, f"AgentSettings.{name} has no fleet agent option"
        flag = "--" + name.removeprefix("agent_").replace("_", "-")
        assert option.opts[0] == flag, option.opts
        assert option.help is not None and option.help.startswith(f"FLEET_{name.upper()}"), option.help
        assert str(field.description) in option.help
        assert option.default is None, "a flag's default would override the environment and the TOML file"
        assert f"{flag} " in help_text and " ".join(option.help.split()) in help_text
    assert options["agent_spool"].opts == ["--spool"] and options["agent_listen"].opts == ["--listen"]
    assert options["agent_token"].help.startswith("FLEET_AGENT_TOKEN or FLEET_TOKEN: ")  # type: ignore[union-attr]
    assert options["agent_api_url"].help.startswith("FLEET_AGENT_API_URL or FLEET_API_URL: ")  # type: ignore[union-attr]
    shared = [n for n in fields if not n.startswith("agent_")]
    for name in shared:  # the spool is the depot's hot tier: its ingest settings apply
        assert options[name].opts[0] == "--" + name.replace("_", "-")
        assert options[name].help.startswith(f"FLEET_{name.upper()}: ")  # type: ignore[union-attr]
    assert set(shared) == {
        "max_message_size",
        "group_commit_ms",
        "close_after_s",
        "secret_fields",
        "default_robot",
        "insecure",
    }
    assert set(SharedSettings.model_fields) < set(shared), "the base's fields: what both programs read"
    assert set(shared) <= set(Settings.model_fields), "a setting the agent shares is the depot's too"
    assert not {n for n in options if n not in fields}, "fleet agent has only the agent's options"
    assert "agent_bandwidth_rules" not in options and "agent_bandwidth_rules" in NOT_OPTIONS
    rules = " ".join(str(fields["agent_bandwidth_rules"].description).split())
    assert f"FLEET_AGENT_BANDWIDTH_RULES {rules}" in help_text  # named after the options, as TOML only


def test_fleet_serve_has_no_agent_option():
    options = _options(serve)
    assert not {n for n in options if n.startswith("agent_")}
    help_text = _help(serve)
    assert "FLEET_AGENT_" not in help_text and "--spool" not in help_text


def test_the_token_and_the_api_url_come_from_the_cli_variables(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    monkeypatch.setenv("FLEET_TOKEN", "robot-7-token")
    monkeypatch.setenv("FLEET_API_URL", "http://depot:8080")
    params = agent.make_context("agent", ["--spool", "s", "--retain-hours", "2"]).params
    given = {k: v for k, v in params.items() if v is not None}
    assert given == {
        "agent_spool": Path("s"),
        "agent_retain_hours": 2.0,
        "agent_token": "robot-7-token",
        "agent_api_url": "http://depot:8080",
    }
    settings = load_agent_settings(**params)
    assert settings.agent_token is not None and settings.agent_token.get_secret_value() == "robot-7-token"
    assert (settings.agent_spool, settings.agent_retain_hours) == (Path("s"), 2.0)


# --- one agent per spool and per port ----------------------------------------------------------------


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    except OSError:
        return False
    return True


def agent_env(spool: Path, listen_port: int, **more: str) -> dict[str, str]:
    """`fleet agent` on loopback ports of its own, its depot a port nothing listens on, no token."""
    env = {k: v for k, v in os.environ.items() if k not in ("FLEET_TOKEN", "FLEET_AGENT_TOKEN", "FLEET_CONFIG")}
    return {
        **env,
        "FLEET_AGENT_SPOOL": str(spool),
        "FLEET_AGENT_LISTEN": f"127.0.0.1:{listen_port}",
        "FLEET_AGENT_STATUS_ADDR": f"127.0.0.1:{free_port()}",
        "FLEET_AGENT_DEPOT": f"rerun+http://127.0.0.1:{free_port()}",  # closed: the agent keeps its runs
        "FLEET_AGENT_MIN_FREE_BYTES": "0",
        **more,
    }


def refused(env: dict[str, str]) -> str:
    """`fleet agent` expected to stop at once: its one line of error."""
    result = subprocess.run([FLEET, "agent"], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 1, (result.returncode, result.stdout[-2000:], result.stderr[-2000:])
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr[-3000:]
    assert "fleet agent: spool" not in result.stdout, "nothing is announced before the refusal"
    return lines[0]


@pytest.fixture
def first_agent(tmp_path: Path) -> Iterator[ServerProcess]:
    port = free_port()
    process = ServerProcess(
        [FLEET, "agent"],
        env=agent_env(tmp_path / "spool", port),
        log=tmp_path / "first-agent.log",
        name="fleet agent",
        ready=lambda: _listening(port),
    )
    process.start(timeout=60)
    yield process
    process.stop(grace=10)


@pytest.mark.slow
def test_a_second_agent_on_the_same_spool_stops_at_once(first_agent: ServerProcess, tmp_path: Path):
    line = refused(agent_env(tmp_path / "spool", free_port()))
    assert line.startswith("Error: the spool is in use by another `fleet agent`")
    assert f"(PID {first_agent.proc.pid})" in line
    assert "--spool or FLEET_AGENT_SPOOL" in line
    assert first_agent.running  # the first goes on


@pytest.fixture
def busy_port() -> Iterator[int]:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen(1)
        yield int(sock.getsockname()[1])


@pytest.mark.slow
def test_a_port_in_use_is_one_line_naming_the_setting(busy_port: int, tmp_path: Path):
    line = refused(agent_env(tmp_path / "spool", busy_port))
    assert f"127.0.0.1:{busy_port}" in line and "already in use" in line
    assert "--listen or FLEET_AGENT_LISTEN" in line  # the agent's flag, without the prefix


def test_a_port_in_use_is_refused_before_anything_starts(
    busy_port: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    spool = tmp_path / "spool"
    result = CliRunner().invoke(agent, ["--spool", str(spool), "--listen", f"127.0.0.1:{busy_port}"])
    assert isinstance(result.exception, ConflictError), result.output
    assert "agent's SDK address" in str(result.exception) and "--listen or FLEET_AGENT_LISTEN" in str(result.exception)
    status = f"127.0.0.1:{busy_port}"
    result = CliRunner().invoke(
        agent, ["--spool", str(spool), "--listen", f"127.0.0.1:{free_port()}", "--status-addr", status]
    )
    assert isinstance(result.exception, ConflictError), result.output
    assert "--status-addr or FLEET_AGENT_STATUS_ADDR" in str(result.exception)
    assert not (spool / "runs").exists(), "refused before the spool is opened"


def test_a_bad_address_is_one_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    result = CliRunner().invoke(agent, ["--spool", str(tmp_path / "spool"), "--listen", "nonsense"])
    assert isinstance(result.exception, InvalidArgumentError), result.output
    assert "HOST:PORT" in str(result.exception) and "--listen" in str(result.exception)


def test_a_list_flag_is_repeatable_and_takes_a_comma_separated_list():
    def parsed(*args: str) -> list[str]:
        flags = agent.make_context("agent", list(args)).params
        return load_agent_settings(**flags).agent_live_include

    assert parsed("--live-include", "/metrics/**", "--live-include", "/logs/**") == ["/metrics/**", "/logs/**"]
    assert parsed("--live-include", "/metrics/**,/logs/**") == ["/metrics/**", "/logs/**"]
    assert parsed() == ["/**"]  # left out: the default, not an empty list


def test_a_listen_address_off_the_robot_is_refused_unless_insecure(tmp_path: Path):
    from services.cli.agent import _check_ports

    listen = {"agent_spool": tmp_path, "agent_listen": "0.0.0.0:0", "agent_status_addr": "127.0.0.1:0"}
    with pytest.raises(InvalidArgumentError, match=r"not a loopback address.*--insecure"):
        _check_ports(load_agent_settings(**listen))
    _check_ports(load_agent_settings(**listen, insecure=True))
