"""deploy/k8s: the same topology as the compose file, checked by structure here, against the
Kubernetes OpenAPI schemas (`kubernetes-validate --strict`, a dev dependency: unknown fields
fail), and rendered by `kubectl kustomize` where kubectl is installed. No cluster is needed."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import ValidationError

from services.settings import load_settings
from tests.deploy.deploy_files import DEPLOY, K8S, PLACEHOLDER, known_names, run, venv_tool, yaml_documents

# The oldest Kubernetes these manifests are for, and the newest schemas the validator bundles.
KUBERNETES_VERSIONS = ("1.29.0", None)
KUSTOMIZATIONS = (K8S, K8S / "try-postgres")


def manifests() -> list[Path]:
    return sorted(p for p in K8S.rglob("*.yaml") if p.name != "kustomization.yaml")


def objects() -> dict[tuple[str, str], dict[str, Any]]:
    found = {}
    for path in manifests():
        for doc in yaml_documents(path):
            found[(doc["kind"], doc["metadata"]["name"])] = doc
    return found


def pod_spec(kind: str, name: str) -> dict[str, Any]:
    spec: dict[str, Any] = objects()[(kind, name)]["spec"]["template"]["spec"]
    return spec


def depot() -> dict[str, Any]:
    (container,) = pod_spec("StatefulSet", "fleet-depot")["containers"]
    found: dict[str, Any] = container
    return found


def settings() -> dict[str, str]:
    data: dict[str, str] = objects()[("ConfigMap", "fleet-settings")]["data"]
    return data


def port(addr: str) -> int:
    return int(addr.rsplit(":", 1)[1])


def test_every_manifest_is_listed_by_its_kustomization_but_the_secret() -> None:
    for root in KUSTOMIZATIONS:
        listed = yaml.safe_load((root / "kustomization.yaml").read_text())["resources"]
        files = {p.name for p in root.glob("*.yaml")} - {"kustomization.yaml"}
        assert set(listed) == files - {"secret.yaml"}, root
    # `kubectl apply -k` must never overwrite the operator's real Secret with the placeholders
    assert "secret.yaml" in {p.name for p in K8S.glob("*.yaml")}


def test_the_depot_is_a_stateful_set_with_a_hot_volume_per_pod() -> None:
    sts = objects()[("StatefulSet", "fleet-depot")]
    (claim,) = sts["spec"]["volumeClaimTemplates"]
    mounts = {m["name"]: m["mountPath"] for m in depot()["volumeMounts"]}
    assert mounts[claim["metadata"]["name"]] == settings()["FLEET_DATA_DIR"]
    assert claim["spec"]["accessModes"] == ["ReadWriteOnce"]
    assert sts["spec"]["replicas"] >= 2
    assert sts["spec"]["serviceName"] == "fleet-depot-peers"
    assert ("Service", "fleet-depot-peers") in objects()


def test_the_node_id_and_peer_address_come_from_the_pod() -> None:
    env = {e["name"]: e["valueFrom"] for e in depot()["env"]}
    assert env["FLEET_NODE_ID"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert env["FLEET_PEER_ADVERTISE"]["fieldRef"]["fieldPath"] == "status.podIP"
    assert env["FLEET_WORKERS"]["resourceFieldRef"]["resource"] == "limits.cpu"
    ports = {p["name"]: p["containerPort"] for p in depot()["ports"]}
    values = settings()
    assert ports == {
        "http": port(values["FLEET_HTTP_ADDR"]),
        "grpc": port(values["FLEET_GRPC_ADDR"]),
        "peer": port(values["FLEET_PEER_ADDR"]),
    }
    policy = objects()[("NetworkPolicy", "fleet-depot")]["spec"]["ingress"]
    peer_rule = [r for r in policy if r.get("from")]
    assert [p["port"] for r in peer_rule for p in r["ports"]] == [ports["peer"]]
    assert peer_rule[0]["from"][0]["podSelector"]["matchLabels"] == {"app.kubernetes.io/name": "fleet-depot"}


def test_probes_termination_and_user() -> None:
    container = depot()
    assert container["readinessProbe"]["httpGet"] == {"path": "/readyz", "port": "http"}
    assert container["livenessProbe"]["httpGet"] == {"path": "/healthz", "port": "http"}
    assert container["startupProbe"]["httpGet"]["path"] == "/healthz"
    spec = pod_spec("StatefulSet", "fleet-depot")
    assert spec["terminationGracePeriodSeconds"] >= 60
    assert spec["securityContext"]["runAsNonRoot"] is True and spec["securityContext"]["runAsUser"] != 0


def test_every_container_requests_cpu_and_memory() -> None:
    for (kind, name), obj in objects().items():
        if kind not in ("StatefulSet", "Deployment", "Job"):
            continue
        spec = obj["spec"]["template"]["spec"]
        for container in spec.get("initContainers", []) + spec["containers"]:
            requests = container["resources"]["requests"]
            assert {"cpu", "memory"} <= set(requests), f"{kind}/{name}: {container['name']} requests no cpu/memory"


def test_the_service_passes_rest_and_grpc_h2c_to_the_depot_pods() -> None:
    service = objects()[("Service", "fleet")]["spec"]
    ports = {p["port"]: p for p in service["ports"]}
    values = settings()
    assert set(ports) == {port(values["FLEET_HTTP_ADDR"]), port(values["FLEET_GRPC_ADDR"])}
    assert ports[port(values["FLEET_GRPC_ADDR"])]["appProtocol"] == "kubernetes.io/h2c"
    labels = objects()[("StatefulSet", "fleet-depot")]["spec"]["template"]["metadata"]["labels"]
    assert service["selector"].items() <= labels.items()


def test_the_migration_job_and_the_nodes_read_the_same_settings() -> None:
    (job,) = pod_spec("Job", "fleet-db-upgrade")["containers"]
    assert job["command"] == ["fleet", "db", "upgrade"]
    assert job["envFrom"] == depot()["envFrom"]
    refs = {next(iter(ref.values()))["name"] for ref in depot()["envFrom"]}
    assert refs == {"fleet-settings", "fleet-secrets"}
    assert ("Secret", "fleet-secrets") in objects() and ("ConfigMap", "fleet-settings") in objects()


def test_the_nodes_wait_for_the_schema_with_code_that_exists() -> None:
    (wait,) = pod_spec("StatefulSet", "fleet-depot")["initContainers"]
    code = wait["command"][2]
    tree = ast.parse(code)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module or "")
            for alias in node.names:
                assert hasattr(module, alias.name), f"{node.module}.{alias.name} no longer exists"
    assert wait["envFrom"] == depot()["envFrom"]


def test_the_secret_holds_placeholders_the_depot_refuses() -> None:
    secret = objects()[("Secret", "fleet-secrets")]
    assert "data" not in secret
    for key, value in secret["stringData"].items():
        assert PLACEHOLDER in value, f"{key} is not a placeholder"
    with pytest.raises(ValidationError, match="at least 32 characters"):
        load_settings(auth_key=secret["stringData"]["FLEET_AUTH_KEY"])


def test_settings_and_secret_keys_are_known_names() -> None:
    keys = set(settings()) | set(objects()[("Secret", "fleet-secrets")]["stringData"])
    unknown = {k for k in keys if not k.startswith("AWS_")} - known_names()
    assert not unknown, sorted(unknown)


def validate(paths: list[Path]) -> None:
    tool = venv_tool("kubernetes-validate")
    if tool is None:
        pytest.fail("kubernetes-validate is missing: pip install -e '.[dev]' installs it")
    for version in KUBERNETES_VERSIONS:
        pinned = ["-k", version] if version else []
        done = run([tool, "--strict", "--quiet", *pinned, *map(str, paths)])
        assert done.returncode == 0, done.stdout + done.stderr


def test_manifests_match_the_kubernetes_schemas() -> None:
    validate(manifests())


def test_kustomize_renders_them(tmp_path: Path) -> None:
    kubectl = venv_tool("kubectl")
    if kubectl is None:
        pytest.skip("kubectl is not installed: the kustomizations are checked by structure only")
    rendered = []
    for root in KUSTOMIZATIONS:
        done = run([kubectl, "kustomize", str(root)])
        assert done.returncode == 0, done.stderr
        out = tmp_path / f"{root.name}.yaml"
        out.write_text(done.stdout)
        rendered.append(out)
        docs = list(yaml.safe_load_all(done.stdout))
        assert all(d["metadata"].get("namespace") == "fleet" for d in docs if d["kind"] != "Namespace")
        assert all(d["metadata"]["labels"]["app.kubernetes.io/part-of"] == "fleet-telemetry" for d in docs)
    workloads = [
        d["spec"]["template"]["spec"]
        for d in yaml.safe_load_all(rendered[0].read_text())
        if "template" in d.get("spec", {})
    ]
    images = {c["image"] for spec in workloads for c in spec.get("initContainers", []) + spec["containers"]}
    assert images == {"registry.example.com/fleet-telemetry:0.1.0"}
    validate(rendered)


def ingress_backends(name: str) -> list[tuple[str, dict[str, Any]]]:
    """(host, backend service) of each path of the Ingress `name`."""
    spec = objects()[("Ingress", name)]["spec"]
    return [(rule["host"], path["backend"]["service"]) for rule in spec["rules"] for path in rule["http"]["paths"]]


def service_port(name: str, ref: dict[str, Any]) -> dict[str, Any]:
    """The port of Service `name` an Ingress backend refers to (by name or number)."""
    for p in objects()[("Service", name)]["spec"]["ports"]:
        if ref.get("name") == p["name"] or ref.get("number") == p["port"]:
            found: dict[str, Any] = p
            return found
    raise AssertionError(f"Service {name} has no port {ref}")


def test_an_ingress_routes_rest_and_another_grpc_h2c_to_the_service() -> None:
    found = objects()
    rest, grpc = found[("Ingress", "fleet")], found[("Ingress", "fleet-grpc")]
    assert grpc["metadata"]["annotations"]["nginx.ingress.kubernetes.io/backend-protocol"] == "GRPC"
    assert rest["metadata"]["annotations"].get("nginx.ingress.kubernetes.io/backend-protocol", "HTTP") == "HTTP"
    values = settings()
    for name, port_name, addr in (("fleet", "http", "FLEET_HTTP_ADDR"), ("fleet-grpc", "grpc", "FLEET_GRPC_ADDR")):
        backends = ingress_backends(name)
        assert backends, name
        for _, backend in backends:
            target = service_port(backend["name"], backend["port"])
            assert target["name"] == port_name and target["port"] == port(values[addr]), (name, target)
        spec = found[("Ingress", name)]["spec"]
        assert spec["ingressClassName"] == "nginx"
        tls_hosts = {h for t in spec["tls"] for h in t["hosts"]}
        assert {host for host, _ in backends} <= tls_hosts, f"{name}: a host without TLS"
    assert service_port("fleet", {"name": "grpc"})["appProtocol"] == "kubernetes.io/h2c"
    # the links the depot hands out name the host the REST Ingress serves
    public = values["FLEET_PUBLIC_URL"].split("://", 1)[1].split("/", 1)[0]
    rest_hosts = {host for host, _ in ingress_backends("fleet")}
    assert public in rest_hosts
    assert rest_hosts.isdisjoint(host for host, _ in ingress_backends("fleet-grpc"))
    # robots' streams last as long as their runs: no short proxy timeout cuts them
    for name in ("fleet", "fleet-grpc"):
        annotations = found[("Ingress", name)]["metadata"]["annotations"]
        assert int(annotations["nginx.ingress.kubernetes.io/proxy-read-timeout"]) >= 3600
        assert annotations["nginx.ingress.kubernetes.io/proxy-body-size"] == "0"


def test_a_job_creates_the_buckets_with_the_script_the_image_holds() -> None:
    (job,) = pod_spec("Job", "fleet-create-buckets")["containers"]
    copied = re.search(r"^COPY deploy/create_buckets\.py (\S+)$", (DEPLOY / "Dockerfile").read_text(), re.M)
    assert copied, "the image no longer holds create_buckets.py"
    assert job["command"][:2] == ["python", copied.group(1)]
    assert "--versioning" in job["command"]
    assert job["envFrom"] == depot()["envFrom"]  # the nodes' store, region and credentials
    # the script makes the buckets the nodes' settings name, and only those
    values = settings()
    assert len(_load_script().bucket_names(values["FLEET_WARM_URL"], values["FLEET_COLD_URL"])) == 2


def _load_script() -> Any:
    spec = importlib.util.spec_from_file_location("create_buckets", DEPLOY / "create_buckets.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
