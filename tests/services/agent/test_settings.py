"""The agent's settings: its own `agent_*` ones under their FLEET_AGENT_* names, the ingest ones it
shares with the depot under theirs, and a TOML file both programs may share on one machine."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from services.agent.settings import AgentSettings, load_agent_settings
from services.settings import Settings, SharedSettings, load_settings


@pytest.fixture(autouse=True)
def _no_config(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FLEET_CONFIG", raising=False)


def test_its_own_settings_are_named_agent():
    own = set(AgentSettings.model_fields) - set(SharedSettings.model_fields) - {"insecure"}
    assert own and all(name.startswith("agent_") for name in own), sorted(own)
    assert not {n for n in Settings.model_fields if n.startswith("agent_")}, "the depot knows no agent setting"


def test_variables_keep_their_names(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    monkeypatch.setenv("FLEET_AGENT_SPOOL", str(tmp_path))
    monkeypatch.setenv("FLEET_AGENT_RETAIN_HOURS", "2")
    monkeypatch.setenv("FLEET_AGENT_LIVE_INCLUDE", "/metrics/**,/logs/**")
    monkeypatch.setenv("FLEET_MAX_MESSAGE_SIZE", "1000")  # shared with the depot
    monkeypatch.setenv("FLEET_INSECURE", "true")
    settings = load_agent_settings()
    assert (settings.agent_spool, settings.agent_retain_hours) == (tmp_path, 2.0)
    assert settings.agent_live_include == ["/metrics/**", "/logs/**"]
    assert (settings.max_message_size, settings.insecure) == (1000, True)
    assert load_agent_settings(agent_retain_hours=3).agent_retain_hours == 3  # flags win


def test_the_depots_variables_do_not_concern_the_agent(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("FLEET_SQL_RATE", "not a rate")  # refused by fleet serve, never read by the agent
    monkeypatch.setenv("FLEET_DATA_DIR", "/nowhere")
    assert load_agent_settings().agent_spool == Path("./fleet-agent")
    with pytest.raises(ValidationError, match="sql_rate"):
        load_settings()


def test_the_agents_variables_do_not_concern_the_depot(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("FLEET_AGENT_RETAIN_HOURS", "-1")  # refused by fleet agent, never read by fleet serve
    monkeypatch.setenv("FLEET_AGENT_SPOOL", "/var/lib/fleet-agent")
    assert load_settings().http_addr == "0.0.0.0:8080"
    with pytest.raises(ValidationError, match="agent_retain_hours"):
        load_agent_settings()


def test_one_toml_file_serves_both_programs(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    config = tmp_path / "fleet.toml"
    config.write_text(
        'http_addr = "127.0.0.1:1111"\nmax_message_size = 2000\nagent_spool = "spool"\n'
        '[[agent_bandwidth_rules]]\ninterface = "eth0"\nbytes_per_s = 0\n'
    )
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    depot, agent = load_settings(), load_agent_settings()
    assert (depot.http_addr, depot.max_message_size) == ("127.0.0.1:1111", 2000)
    assert (agent.agent_spool, agent.max_message_size) == (Path("spool"), 2000)
    assert agent.agent_bandwidth_rules == [{"interface": "eth0", "bytes_per_s": 0}]


@pytest.mark.parametrize("typo", ["agent_spoool", "htp_addr"])
def test_a_key_neither_program_reads_is_refused_by_the_agent(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, typo: str
):
    config = tmp_path / "fleet.toml"
    config.write_text(f'{typo} = "x"\n')
    monkeypatch.setenv("FLEET_CONFIG", str(config))
    with pytest.raises(ValidationError, match=typo):
        load_agent_settings()
