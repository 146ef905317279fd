"""deploy/compose.yaml, its load balancer, image and .env, the names every deployment file uses,
and docs/deploy.md: checked by structure here, and by real Compose validators where installed
(`check-jsonschema` with the Compose specification's schema, a dev dependency; `docker-compose
config`, Debian's package, which .ci/run installs). No container is started."""

from __future__ import annotations

import os
import re
import shutil
import stat
from pathlib import Path
from typing import Any

import pytest
import yaml

from services.settings import load_settings
from tests.deploy.deploy_files import (
    DEPLOY,
    DOCS,
    OTHER_VARIABLES,
    ROOT,
    build_sources,
    compose_validators,
    deploy_files,
    fleet_names,
    known_names,
    parse_nginx,
    readme_section,
    run,
    seconds,
    secret_like,
    venv_tool,
)

COMPOSE = DEPLOY / "compose.yaml"
PRODUCTION = "Production: several nodes (Compose or Kubernetes)"
SECRET_VARIABLE = re.compile(r"KEY|SECRET|PASSWORD|TOKEN")


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    loaded: dict[str, Any] = yaml.safe_load(COMPOSE.read_text())
    return loaded


def services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    found: dict[str, dict[str, Any]] = compose["services"]
    return found


def nodes(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {name: s for name, s in services(compose).items() if s.get("command") == ["fleet", "serve"]}


def one_shots(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {name: s for name, s in services(compose).items() if s.get("restart") == "no"}


def reference(value: str) -> bool:
    return re.fullmatch(r"\$\{[A-Z0-9_]+(:?[-?][^}]*)?\}", value) is not None


@pytest.fixture
def env_file(tmp_path: Path) -> Path:
    """deploy/.env as the documented `deploy/make-env.sh` writes it, in a scratch copy."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: deploy/make-env.sh needs it")
    for name in ("make-env.sh", ".env.example"):
        shutil.copy2(DEPLOY / name, tmp_path / name)
    done = run(["sh", str(tmp_path / "make-env.sh")])
    assert done.returncode == 0, done.stderr
    return tmp_path / ".env"


def env_values(path: Path) -> dict[str, str]:
    lines = [line for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    return dict(line.split("=", 1) for line in lines)


# ---- the topology


def test_long_running_services_have_healthchecks_and_one_shots_gate_the_nodes(compose: dict[str, Any]) -> None:
    shots = one_shots(compose)
    assert {tuple(s["command"][:3]) for s in shots.values()} >= {("fleet", "db", "upgrade")}
    for name, service in services(compose).items():
        if name in shots:
            continue  # a one-shot exits: what it must gate is checked below instead
        test = service.get("healthcheck", {}).get("test")
        assert test and test[0] in ("CMD", "CMD-SHELL") and len(test) > 1, f"{name} has no healthcheck"
    for name, node in nodes(compose).items():
        gates = {dep: cond["condition"] for dep, cond in node["depends_on"].items()}
        for shot in shots:
            assert gates.get(shot) == "service_completed_successfully", f"{name} starts before {shot} is done"


def test_each_node_has_its_own_hot_volume_name_and_peer_address(compose: dict[str, Any]) -> None:
    depot = nodes(compose)
    assert len(depot) >= 2
    volumes, ids = [], []
    for name, node in depot.items():
        env = node["environment"]
        data_dir = env["FLEET_DATA_DIR"]
        mounts = [m.split(":") for m in node["volumes"]]
        hot = [src for src, dst, *_ in mounts if dst == data_dir]
        assert len(hot) == 1 and hot[0] in compose["volumes"], f"{name}: no named volume at {data_dir}"
        volumes.append(hot[0])
        ids.append(env["FLEET_NODE_ID"])
        assert env["FLEET_PEER_ADVERTISE"] == node["hostname"] == env["FLEET_NODE_ID"]
        assert env["FLEET_PEER_ADDR"].startswith("0.0.0.0:")
        assert "ports" not in node, f"{name} publishes ports: only the load balancer may"
        assert node["stop_grace_period"] in ("2m", "120s")
    assert len(set(volumes)) == len(volumes), f"nodes share a hot volume: {volumes}"
    assert len(set(ids)) == len(ids)


def test_every_depot_process_reaches_the_same_catalog_store_and_key(compose: dict[str, Any]) -> None:
    image = {name: s for name, s in services(compose).items() if s.get("build", {}).get("dockerfile")}
    assert set(nodes(compose)) | set(one_shots(compose)) <= set(image)
    for key in ("FLEET_CATALOG_URL", "FLEET_WARM_URL", "FLEET_COLD_URL", "FLEET_S3_ENDPOINT_URL", "FLEET_AUTH_KEY"):
        assert len({s["environment"][key] for s in image.values()}) == 1, f"{key} differs between processes"
    env = next(iter(image.values()))["environment"]
    assert "@postgres:5432/" in env["FLEET_CATALOG_URL"] and env["FLEET_CATALOG_URL"].startswith(
        "postgresql+psycopg://"
    )
    assert env["FLEET_S3_ENDPOINT_URL"] == "http://s3:8333"
    assert {"postgres", "s3"} <= set(services(compose))


def test_no_literal_secret_in_compose(compose: dict[str, Any]) -> None:
    for name, service in services(compose).items():
        for key, value in (service.get("environment") or {}).items():
            if SECRET_VARIABLE.search(key):
                assert reference(str(value)), f"{name}: {key} must come from deploy/.env (${{...}})"
        url = (service.get("environment") or {}).get("FLEET_CATALOG_URL")
        if url:
            password = re.search(r"://[^:@/]+:([^@]+)@", url)
            assert password and reference(password.group(1)), f"{name}: the catalog URL's password is not a reference"


def test_only_the_load_balancer_publishes_rest_and_grpc(compose: dict[str, Any]) -> None:
    published = {name: s["ports"] for name, s in services(compose).items() if s.get("ports")}
    assert list(published) == ["lb"]
    assert {p.rsplit(":", 1)[1] for p in published["lb"]} == {"8080", "51234"}
    assert "./nginx.conf:/etc/nginx/nginx.conf:ro" in services(compose)["lb"]["volumes"]


def test_the_load_balancer_sends_both_ports_to_every_node(compose: dict[str, Any]) -> None:
    config = parse_nginx((DEPLOY / "nginx.conf").read_text())
    (http,) = config.children("http")
    upstreams = {u.args[0]: [s[0] for s in u.values("server")] for u in http.children("upstream")}
    hosts = {s["hostname"] for s in nodes(compose).values()}
    servers = {s.value("listen")[0]: s for s in http.children("server")}  # type: ignore[index]
    assert set(servers) == {"8080", "51234"}

    rest = servers["8080"]
    (location,) = rest.children("location")
    target = location.value("proxy_pass")[0].removeprefix("http://")  # type: ignore[index]
    assert sorted(upstreams[target]) == sorted(f"{h}:8080" for h in hosts)
    assert rest.value("client_max_body_size") == ["0"]  # uploads of whole recordings
    assert rest.value("proxy_request_buffering") == rest.value("proxy_buffering") == ["off"]

    grpc = servers["51234"]
    assert grpc.value("http2") == ["on"]
    assert grpc.value("client_max_body_size") == ["0"]  # a robot's stream is one request body for hours
    assert seconds(grpc.value("grpc_read_timeout")[0]) >= 3600  # type: ignore[index]
    assert seconds(grpc.value("grpc_send_timeout")[0]) >= 3600  # type: ignore[index]
    passes = [loc.value("grpc_pass") for loc in grpc.children("location") if loc.value("grpc_pass")]
    assert passes and passes[0][0].startswith("grpc://")  # type: ignore[index]
    assert sorted(upstreams[passes[0][0].removeprefix("grpc://")]) == sorted(f"{h}:51234" for h in hosts)  # type: ignore[index]


def test_the_image_installs_the_compiled_package_as_a_non_root_user() -> None:
    text = (DEPLOY / "Dockerfile").read_text().replace("\\\n", " ")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and ln.strip()[0] != "#"]
    stages = [ln for ln in lines if ln.startswith("FROM ")]
    assert stages == ["FROM python:3.11-slim AS build", "FROM python:3.11-slim"]
    build, image = lines[: lines.index(stages[1])], lines[lines.index(stages[1]) :]
    assert "RUN FLEET_COMPILE=1 pip wheel --no-deps --wheel-dir /wheels ." in build  # the ingest path compiled
    assert "COPY --from=build /wheels /wheels" in image
    assert any(re.match(r"RUN pip install /wheels/\*\.whl( |$)", ln) for ln in image)
    assert not any("gcc" in ln for ln in image)  # the compiler stays in the build stage
    users = [ln.split()[1] for ln in image if ln.startswith("USER ")]
    assert users and users[-1].split(":")[0] not in ("root", "0")
    sources = [ln for ln in lines if ln.startswith("COPY ") and not ln.startswith("COPY --from")]
    copied = {ln.split()[1] for ln in sources} | {name for ln in sources for name in ln.split()[1:-1]}
    packages, beside = build_sources()
    needed = {*packages, *beside}
    assert needed <= copied, f"the image lacks {sorted(needed - copied)}: pip install . would miss them"
    for source in copied:
        assert (ROOT / source).exists(), source
    kept = {ln[1:] for ln in (DEPLOY / "Dockerfile.dockerignore").read_text().splitlines() if ln.startswith("!")}
    assert copied <= kept, f"the build context leaves out {sorted(copied - kept)}"


# ---- settings names and secrets, in every file this deployment ships


def test_every_setting_named_exists() -> None:
    for name, source in OTHER_VARIABLES.items():
        assert name in (ROOT / source).read_text(), f"{name} is no longer read by {source}"
    known = known_names()
    texts = {p: p.read_text() for p in [*deploy_files(), DOCS]}
    texts[ROOT / "README.md"] = readme_section(PRODUCTION)
    for path, text in texts.items():
        unknown = fleet_names(text) - known
        assert not unknown, f"{path.relative_to(ROOT)} names settings that do not exist: {sorted(unknown)}"


def test_no_file_holds_a_real_secret() -> None:
    for path in [*deploy_files(), DOCS]:
        assert not secret_like(path.read_text()), f"{path.relative_to(ROOT)} holds what looks like a secret"


def test_env_example_leaves_the_secrets_empty_and_defines_every_variable(compose: dict[str, Any]) -> None:
    example = env_values(DEPLOY / ".env.example")
    for name in ("FLEET_AUTH_KEY", "POSTGRES_PASSWORD", "S3_SECRET_ACCESS_KEY"):
        assert example[name] == "", f"{name} has a value in .env.example"
    used = set(re.findall(r"\$\{([A-Z0-9_]+)", COMPOSE.read_text()))
    assert used <= set(example), f"compose.yaml reads {sorted(used - set(example))}, not in .env.example"
    assert ".env" in (DEPLOY / ".gitignore").read_text().splitlines()


def test_make_env_writes_fresh_secrets_once(env_file: Path) -> None:
    assert stat.S_IMODE(env_file.stat().st_mode) == 0o600
    values = env_values(env_file)
    secrets = [values[n] for n in ("FLEET_AUTH_KEY", "POSTGRES_PASSWORD", "S3_SECRET_ACCESS_KEY")]
    assert all(re.fullmatch(r"[0-9a-f]{64}", s) for s in secrets) and len(set(secrets)) == 3
    assert load_settings(auth_key=values["FLEET_AUTH_KEY"]).auth_key is not None
    before = env_file.read_text()
    again = run(["sh", str(env_file.with_name("make-env.sh"))])
    assert again.returncode == 1 and "left as it is" in again.stderr
    assert env_file.read_text() == before  # the key that signed every token is never replaced


# ---- the real validators


def test_compose_file_matches_the_compose_specification() -> None:
    tool = venv_tool("check-jsonschema")
    if tool is None:
        pytest.fail("check-jsonschema is missing: pip install -e '.[dev]' installs it")
    done = run([tool, "--builtin-schema", "vendor.compose-spec", str(COMPOSE)])
    assert done.returncode == 0, done.stdout + done.stderr


def test_compose_config_accepts_the_file_with_a_made_env_and_refuses_it_without_secrets(env_file: Path) -> None:
    validators = compose_validators()
    if not validators:
        pytest.skip("neither `docker compose` nor `docker-compose` is installed (.ci/run installs docker-compose)")
    for compose in validators:
        done = run([*compose, "--env-file", str(env_file), "-f", str(COMPOSE), "config", "-q"])
        assert done.returncode == 0, f"{' '.join(compose)} config: {done.stderr}"
        bare = run([*compose, "--env-file", str(DEPLOY / ".env.example"), "-f", str(COMPOSE), "config", "-q"])
        assert bare.returncode != 0 and "make-env.sh" in bare.stdout + bare.stderr


# ---- docs and the README


def test_docs_and_readme_link_to_files_that_exist() -> None:
    section = readme_section(PRODUCTION)
    for command in ("deploy/make-env.sh", "docker compose -f deploy/compose.yaml up", "fleet tokens create"):
        assert command in section
    for base, text in ((DOCS.parent, DOCS.read_text()), (ROOT, section)):
        for target in re.findall(r"\]\(([^)#\s]+)", text):
            if "://" not in target:
                assert (base / target).exists(), f"a link to {target} from {base}"


def test_the_readme_keeps_its_first_two_commands() -> None:
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    assert blocks[0].strip() == "python3 -m venv .venv && .venv/bin/pip install -e '.[dev]' && .venv/bin/fleet serve"
    assert blocks[1].startswith(". .venv/bin/activate\nfleet runs ls")
    assert text.index(f"## {PRODUCTION}") > text.index(blocks[1])


def test_make_env_is_executable() -> None:
    assert os.access(DEPLOY / "make-env.sh", os.X_OK)
