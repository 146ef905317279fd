"""The agent's example deployment (deploy/agent): its config file is valid settings with bandwidth
rules the agent accepts, and its environment file holds no secret."""

from __future__ import annotations

import datetime as dt
import os
from pathlib import Path

import pytest

from services.agent.bandwidth import RateSchedule
from services.agent.settings import load_agent_settings
from services.settings import Durability

DEPLOY = Path(__file__).resolve().parents[3] / "deploy" / "agent"


@pytest.fixture
def config(monkeypatch: pytest.MonkeyPatch) -> Path:
    for name in ("FLEET_TOKEN", "FLEET_API_URL"):
        monkeypatch.delenv(name, raising=False)
    for name in [n for n in os.environ if n.startswith("FLEET_AGENT_")]:
        monkeypatch.delenv(name)  # only the file speaks
    path = DEPLOY / "agent.toml"
    monkeypatch.setenv("FLEET_CONFIG", str(path))
    return path


def test_the_example_config_loads_into_settings(config: Path):
    settings = load_agent_settings()
    assert settings.agent_spool == Path("/var/lib/fleet-agent")
    assert settings.agent_listen == "127.0.0.1:9876" and settings.agent_status_addr == "127.0.0.1:9877"
    assert settings.agent_depot == "rerun+http://fleet:51234" and settings.agent_api_url == "http://fleet:8080"
    assert settings.agent_watch == [Path("/var/spool/robot")]
    assert settings.agent_retain_hours == 24 and settings.agent_max_bytes == 50_000_000_000
    assert settings.agent_min_free_bytes == 2_000_000_000 and settings.agent_durability is Durability.INTERVAL
    assert settings.agent_live_include == ["/metrics/**", "/logs/**", "/tf/**"]
    assert settings.agent_token is None  # the token never lives in the config file
    assert settings.agent_bandwidth_rules == [{"interface": "eth0", "bytes_per_s": 0}]


def test_its_bandwidth_rules_are_what_the_agent_runs_with(config: Path, tmp_path: Path):
    settings = load_agent_settings()
    sysfs = tmp_path / "net"
    (sysfs / "eth0").mkdir(parents=True)
    schedule = RateSchedule.from_config(settings.agent_bandwidth_rules, settings.agent_bandwidth, sysfs_root=sysfs)
    assert len(schedule.rules) == 1 and schedule.rules[0].interface == "eth0"
    assert schedule.default == 200_000
    noon = dt.time(12, 0)
    (sysfs / "eth0" / "operstate").write_text("down\n")
    assert schedule.rate_at(noon) == 200_000  # cellular: the cap
    (sysfs / "eth0" / "operstate").write_text("up\n")
    docked = RateSchedule.from_config(settings.agent_bandwidth_rules, settings.agent_bandwidth, sysfs_root=sysfs)
    assert docked.rate_at(noon) is None  # the dock's wired network: no cap (a new schedule: no cached state)


def test_the_env_file_holds_no_token():
    lines = [line.strip() for line in (DEPLOY / "fleet-agent.env").read_text().splitlines()]
    settings = dict(line.split("=", 1) for line in lines if line and not line.startswith("#"))
    assert settings["FLEET_TOKEN"] == ""  # filled in on the robot, never in the repository
    assert settings["FLEET_CONFIG"] == "/etc/fleet/agent.toml"
    assert not [k for k in settings if k != "FLEET_TOKEN" and ("TOKEN" in k or "KEY" in k or "SECRET" in k)]


def test_the_unit_reads_the_env_file_and_runs_the_agent():
    unit = (DEPLOY / "fleet-agent.service").read_text()
    assert "EnvironmentFile=/etc/fleet/agent.env" in unit
    assert "ExecStart=/opt/fleet/bin/fleet agent" in unit
    assert "ReadWritePaths=/var/lib/fleet-agent /var/spool/robot" in unit  # the spool and the watched folder
