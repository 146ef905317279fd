"""deploy/agent: every user, group and path fleet-agent.service (and the agent.toml it reads) names
is made by the documented install steps (deploy/agent/install.sh, run here as a dry run: it prints
its commands), or by systemd itself (StateDirectory=)."""

from __future__ import annotations

import configparser
import os
import shlex
import subprocess
import tomllib
from pathlib import Path

from tests.deploy.deploy_files import DEPLOY, ROOT

AGENT = DEPLOY / "agent"
INSTALL = AGENT / "install.sh"


def unit() -> configparser.SectionProxy:
    parser = configparser.ConfigParser(interpolation=None, strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # systemd keys are case-sensitive
    parser.read_string((AGENT / "fleet-agent.service").read_text())
    return parser["Service"]


def install_steps() -> list[list[str]]:
    done = subprocess.run(["sh", str(INSTALL), "--dry-run"], capture_output=True, text=True, timeout=60, check=True)
    return [shlex.split(line) for line in done.stdout.splitlines() if line]


def made_dirs(steps: list[list[str]]) -> set[str]:
    """Directories the steps create: `install -d ... DIR`, a venv's folder, the files they install."""
    dirs: set[str] = set()
    for step in steps:
        if step[0] == "install" and "-d" in step:
            dirs.add(step[-1])
        elif step[1:3] == ["-m", "venv"]:
            dirs.add(step[3])
    return dirs


def installed_files(steps: list[list[str]]) -> set[str]:
    return {step[-1] for step in steps if step[0] == "install" and "-d" not in step}


def owner_of(steps: list[list[str]], path: str) -> str | None:
    for step in steps:
        if step[0] == "install" and step[-1] == path and "-o" in step:
            return step[step.index("-o") + 1]
    return None


def state_dirs() -> set[str]:
    return {f"/var/lib/{name}" for name in unit().get("StateDirectory", "").split()}


def test_the_install_script_is_executable_and_parses() -> None:
    assert os.access(INSTALL, os.X_OK)
    assert subprocess.run(["sh", "-n", str(INSTALL)], capture_output=True, timeout=30).returncode == 0


def test_the_user_and_group_the_unit_runs_as_are_created() -> None:
    service, steps = unit(), install_steps()
    groups = {step[-1] for step in steps if step[0] == "groupadd"}
    users = {step[-1]: step for step in steps if step[0] == "useradd"}
    assert service["Group"] in groups
    assert service["User"] in users
    useradd = users[service["User"]]
    assert useradd[useradd.index("--gid") + 1] == service["Group"]
    assert "--system" in useradd


def test_the_program_the_unit_starts_is_installed() -> None:
    program = shlex.split(unit()["ExecStart"])[0]
    steps = install_steps()
    venv = next(d for d in made_dirs(steps) if program.startswith(d + "/bin/"))
    pip = [s for s in steps if s[0] == f"{venv}/bin/pip" and s[1] == "install"]
    assert pip, f"nothing installs the package into {venv}, so {program} would not exist"
    assert Path(pip[0][-1]) == ROOT  # from this checkout by default (FLEET_PACKAGE for a wheel)


def test_every_path_the_unit_names_is_made() -> None:
    service, steps = unit(), install_steps()
    made = made_dirs(steps) | state_dirs()
    for path in service["ReadWritePaths"].split():
        assert path in made, f"ReadWritePaths {path} is made by no install step"
    (env_file,) = service["EnvironmentFile"].split()
    assert env_file in installed_files(steps)
    assert str(Path(env_file).parent) in made


def test_the_agents_settings_name_paths_that_are_made_and_writable() -> None:
    steps = install_steps()
    env = dict(line.split("=", 1) for line in (AGENT / "fleet-agent.env").read_text().splitlines() if "=" in line[:40])
    config = env["FLEET_CONFIG"]
    assert config in installed_files(steps)
    settings = tomllib.loads((AGENT / "agent.toml").read_text())
    writable = set(unit()["ReadWritePaths"].split())
    assert settings["agent_spool"] in state_dirs() and settings["agent_spool"] in writable
    for folder in settings["agent_watch"]:
        assert folder in made_dirs(steps) and folder in writable
        assert owner_of(steps, folder) == unit()["User"]


def test_the_docs_give_the_install_steps() -> None:
    text = (ROOT / "docs" / "agent.md").read_text()
    assert "deploy/agent/install.sh" in text
    for name in ("fleet-agent", "/opt/fleet", "/var/spool/robot"):
        assert name in text, f"docs/agent.md does not say how {name} is made"
