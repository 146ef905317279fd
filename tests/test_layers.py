"""The dependency rule, enforced: data flows one way, and a layer imports only layers below it.

    core                             errors and their status table, ids, the clock
    rrd, storage, policies, startup, runtime, routine_logs, compiled
                                     the wire codec; object stores; retention policies (plain
                                     values); the data dir lock and the ports; process tuning; the
                                     agent's routine calls at DEBUG; the modules mypyc compiles
    sdk_client, catalog, settings    the client (core only, so it ships without the server); the
                                     catalog (core only); the depot's Settings and the
                                     base it shares with the agent's
    auth | hot | cluster | facts | rules | lakehouse | migrations
                                     tokens, scopes, signed links | the hot tier | run ownership
                                     among nodes | what a run is, learnt from its messages | the
                                     rules language, what it makes of a run's chunks | the
                                     analytics tables as Iceberg tables | the catalog's schema
                                     migrations
    ingest | sealed                  streams and uploads into the hot tier, owning the live runs |
                                     the sealed-run format (recording, chunk index, run.json) and
                                     its tiers
    node                             what the sides of one node share: settings, catalog, stores,
                                     clock, auth
    analytics                        extraction at promotion, SQL over what was extracted
    retention | runs | edge | webhooks | imports
                                     promotion, archive, expiry | serving runs | robots' own tiers |
                                     telling endpoints of what happens, signed | uploads (RRD,
                                     MCAP) as imports
    corpus | datasets                what rules make of runs: events, metrics; people's events and tags |
                                     dataset snapshots: selections resolved into immutable episodes
    api | redap | agent | console | mcp_server
                                     the REST app and the gRPC port's front | the Rerun catalog
                                     server | `fleet agent`, on the robot | the web console | the
                                     MCP server for AI assistants
    server -> workers -> cli         the wiring; `fleet serve --workers N`; the command line

A line is a layer (`->` starts the next one). The same table is drawn in docs/architecture.md ("The
dependency rule"); tests/test_architecture_doc.py checks that both drawings are LAYERS below.

An import from a layer to one above it, or between two modules of one layer (other than within a
package), fails this test, which names the file and the import. Imports inside functions and under
TYPE_CHECKING count too: they are dependencies all the same.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("core", "catalog", "sdk_client", "services", "migrations")

# unit -> layer: a unit imports only units of lower layers (or itself).
LAYERS: dict[str, int] = {
    "core": 0,
    "services": 0,  # the package itself: only its version
    "services.rrd": 1,
    "services.storage": 1,
    "services.policies": 1,
    "services.runtime": 1,
    "services.startup": 1,
    "services.routine_logs": 1,
    "services.compiled": 1,  # names modules of several layers; imports none of them
    "sdk_client": 2,
    "catalog": 2,
    "services.settings": 2,
    "migrations": 3,
    "services.auth": 3,
    "services.hot": 3,
    "services.cluster": 3,
    "services.facts": 3,
    "services.rules": 3,
    "services.lakehouse": 3,
    "services.ingest": 4,
    "services.sealed": 4,
    "services.node": 5,
    "services.analytics": 6,
    "services.retention": 7,
    "services.runs": 7,
    "services.edge": 7,
    "services.webhooks": 7,
    "services.imports": 7,
    "services.corpus": 8,
    "services.datasets": 8,
    "services.api": 9,
    "services.redap": 9,
    "services.agent": 9,
    "services.console": 9,
    "services.mcp_server": 9,
    "services.server": 10,
    "services.workers": 11,
    "services.cli": 12,
}
# Besides the layers: what may a unit import from our packages at all.
ONLY = {"sdk_client": {"core"}, "catalog": {"core"}}


def unit_of(module: str) -> str:
    parts = module.split(".")
    if parts[0] == "services" and len(parts) > 1:
        return f"services.{parts[1]}"
    return parts[0]


def imports() -> list[tuple[Path, str, str]]:
    """(file, importing unit, imported module) for every import of our packages."""
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            module = module_of(path)
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                elif isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                else:
                    continue
                found += [(path, unit_of(module), name) for name in names if name.split(".")[0] in PACKAGES]
    return found


def module_of(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    return ".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts)


def test_every_unit_has_a_layer():
    units = {unit_of(module_of(p)) for package in PACKAGES for p in (ROOT / package).rglob("*.py")}
    assert units <= set(LAYERS), f"give these a layer in {Path(__file__).name}: {sorted(units - set(LAYERS))}"


def violations(found: list[tuple[Path, str, str]]) -> list[str]:
    wrong = []
    for path, unit, module in found:
        target = unit_of(module)
        if target == unit:
            continue
        if unit in ONLY and target not in ONLY[unit]:
            wrong.append(f"{path.relative_to(ROOT)}: {unit} imports {module}, but may import only {sorted(ONLY[unit])}")
        elif LAYERS[target] >= LAYERS[unit]:
            wrong.append(
                f"{path.relative_to(ROOT)}: {unit} (layer {LAYERS[unit]}) imports {module} "
                f"(layer {LAYERS[target]}): lower layers never import higher ones"
            )
    return wrong


def test_imports_go_down_only():
    wrong = violations(imports())
    assert not wrong, "\n".join(wrong)


def test_no_cycle_between_top_level_packages():
    graph: dict[str, set[str]] = {package: set() for package in PACKAGES}
    for path, _, module in imports():
        source, target = path.relative_to(ROOT).parts[0], module.split(".")[0]
        if source != target:
            graph[source].add(target)

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        return any(nxt == goal or (nxt not in seen and reaches(nxt, goal, seen | {nxt})) for nxt in graph[start])

    cycles = [package for package in PACKAGES if reaches(package, package, {package})]
    assert not cycles, f"import cycles through {cycles}: {graph}"


def test_the_rule_names_upward_and_sideways_imports():
    here = ROOT / "services" / "runs" / "service.py"
    assert violations([(here, "services.runs", "services.runs.download")]) == []  # within a package
    assert violations([(here, "services.runs", "services.sealed.read")]) == []  # downward
    upward = violations([(ROOT / "catalog" / "queries.py", "catalog", "services.ingest.service")])
    assert upward == ["catalog/queries.py: catalog imports services.ingest.service, but may import only ['core']"]
    sideways = violations([(here, "services.runs", "services.retention.tiers")])
    assert sideways and "lower layers never import higher ones" in sideways[0]
