"""What the deployment-file tests share: the files, the setting names they may use, a reader of
nginx's configuration, and the external validators (found, or a reason why not)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from services.settings import Settings

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
K8S = DEPLOY / "k8s"
DOCS = ROOT / "docs" / "deploy.md"


def build_sources() -> tuple[list[str], list[str]]:
    """What pip builds the package from: its package folders (pyproject's `packages.find`), and the
    files beside them (pyproject.toml, setup.py, the readme it names)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]]
    return packages, ["pyproject.toml", "setup.py", project["project"]["readme"]]


# Settings of the multi-node depot (run ownership leases, worker processes, the peer port): the
# deployment files name them before `Settings` has them; once it does, the check below still holds.
MULTI_NODE_SETTINGS = frozenset(
    {"FLEET_WORKERS", "FLEET_NODE_ID", "FLEET_PEER_ADDR", "FLEET_PEER_ADVERTISE", "FLEET_LEASE_S"}
)
# Variables read outside `Settings`, each by the file named (checked to still be there).
OTHER_VARIABLES = {
    "FLEET_TOKEN": "services/cli/client.py",
    "FLEET_API_URL": "services/cli/client.py",
    "FLEET_CONFIG": "services/settings.py",
    "FLEET_COMPILE": "setup.py",
}

FLEET_NAME = re.compile(r"\bFLEET_[A-Z0-9_]*[A-Z0-9]\b")
JWT = re.compile(r"eyJ[A-Za-z0-9_-]{8,}\.[A-Za-z0-9_-]{8,}")
LONG_RUN = re.compile(r"(?<![A-Za-z0-9+=_-])[A-Za-z0-9+=_-]{32,}(?![A-Za-z0-9+=_-])")
PLACEHOLDER = "CHANGE-ME"


def settings_names() -> set[str]:
    prefix = str(Settings.model_config.get("env_prefix", ""))
    return {prefix + name.upper() for name in Settings.model_fields}


def known_names() -> set[str]:
    return settings_names() | MULTI_NODE_SETTINGS | set(OTHER_VARIABLES)


def fleet_names(text: str) -> set[str]:
    return set(FLEET_NAME.findall(text))


def deploy_files() -> list[Path]:
    """Every text file this deployment ships (deploy/agent/ is the robot's, tested elsewhere)."""
    files = [p for p in sorted(DEPLOY.rglob("*")) if p.is_file() and "agent" not in p.relative_to(DEPLOY).parts]
    return [p for p in files if p.name != ".env"]  # a local deploy/.env is the operator's, never committed


def secret_like(text: str) -> list[str]:
    """Strings that look like a real token or key: a JWT, or 32+ characters of letters and digits mixed."""
    found = JWT.findall(text)
    for run in LONG_RUN.findall(text):
        if sum(c.isdigit() for c in run) >= 4 and sum(c.isalpha() for c in run) >= 4:
            found.append(run)
    return found


def yaml_documents(path: Path) -> list[dict[str, Any]]:
    return [doc for doc in yaml.safe_load_all(path.read_text()) if doc is not None]


def readme_section(title: str) -> str:
    """The README section under `## {title}`, up to the next `## ` heading."""
    text = (ROOT / "README.md").read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end != -1 else len(text)]


@dataclass
class Block:
    """One block of an nginx configuration: its directives in order and the blocks inside it."""

    name: str
    args: list[str]
    directives: list[tuple[str, list[str]]] = field(default_factory=list)
    blocks: list[Block] = field(default_factory=list)

    def values(self, name: str) -> list[list[str]]:
        return [args for directive, args in self.directives if directive == name]

    def value(self, name: str) -> list[str] | None:
        found = self.values(name)
        return found[-1] if found else None

    def children(self, name: str) -> list[Block]:
        return [b for b in self.blocks if b.name == name]


def parse_nginx(text: str) -> Block:
    """nginx's configuration syntax, enough for these files: words, quoted strings, `;`, `{ }`, comments."""
    tokens = re.findall(r'"[^"]*"|\'[^\']*\'|[{};]|[^\s{};"\']+', re.sub(r"(?m)#.*$", "", text))
    root = Block("main", [])
    stack: list[Block] = [root]
    words: list[str] = []
    for token in tokens:
        if token == ";":
            stack[-1].directives.append((words[0], words[1:]))
            words = []
        elif token == "{":
            block = Block(words[0], words[1:])
            stack[-1].blocks.append(block)
            stack.append(block)
            words = []
        elif token == "}":
            assert not words, f"unterminated directive {words}"
            stack.pop()
        else:
            words.append(token.strip("\"'"))
    assert len(stack) == 1 and not words, "unbalanced braces"
    return root


def seconds(value: str) -> float:
    """An nginx time (`30s`, `10m`, `24h`, `1d`, `500ms`) in seconds."""
    number, unit = re.fullmatch(r"(\d+)(ms|s|m|h|d)?", value).groups()  # type: ignore[union-attr]
    return int(number) * {"ms": 0.001, None: 1, "s": 1, "m": 60, "h": 3600, "d": 86400}[unit]


def tool_env() -> dict[str, str]:
    """A small environment for external tools, so no variable of the test run (FLEET_*, a
    KUBECONFIG) changes what they read."""
    return {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": os.environ.get("HOME", "/tmp"), "LANG": "C.UTF-8"}


def venv_tool(name: str) -> str | None:
    """A console script of this interpreter's environment (a dev dependency), else on PATH."""
    candidate = Path(sys.executable).with_name(name)
    return str(candidate) if candidate.is_file() else shutil.which(name)


def run(argv: list[str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, timeout=120, env=tool_env(), check=False, **kwargs)


def compose_validators() -> list[list[str]]:
    """The Compose implementations here that validate a file without an engine: `docker compose`
    (v2 plugin) and `docker-compose` (v1, Debian's package; .ci/run installs it)."""
    found = []
    docker = shutil.which("docker")
    if docker is not None and run([docker, "compose", "version"]).returncode == 0:
        found.append([docker, "compose"])
    legacy = shutil.which("docker-compose")
    if legacy is not None:
        found.append([legacy])
    return found
