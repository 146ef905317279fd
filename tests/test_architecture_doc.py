"""docs/architecture.md is the map a newcomer reads first, so it must be the tree as it is: every
package, module and class it names exists, every package (and top-level module of `services/`) is
named in it, and its layer table is `tests/test_layers.py`'s (as is that file's own docstring).

What counts as naming, so the doc stays readable prose:
- the packages table: its first column names a package (`services/hot/`) or top-level modules
  (`services/server.py`, `startup.py`); a backticked `x.py` or `x/` in a row is the row's package's
  (or, written from the top, `catalog/nodes.py`, the repository's);
- anywhere: a backticked path from the top (`core/states.py`) and a backticked dotted name whose
  first part is a package (`hot.read.HotRuns`, `catalog.models.Run`: a module, or a module and
  what it defines);
- the data path's drawing: `hot/store`, a package's module;
- the layer table, the code block under "The dependency rule": a line is a layer, `->` starts the
  next one, `,` and `|` separate the units of one layer, parentheses hold comments.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable, Iterator
from pathlib import Path

from tests.test_layers import LAYERS, PACKAGES, ROOT
from tests.test_layers import __doc__ as LAYERS_DOC

DOC = ROOT / "docs" / "architecture.md"
TOP = tuple(p for p in PACKAGES if p != "services")  # top-level packages (services' own are below it)
TICKED = re.compile(r"`([^`\n]+)`")
PATHLIKE = re.compile(r"[\w./-]*\w(\.py|/)")
DOTTED = re.compile(r"[a-z_]\w*(\.\w+)+")
DRAWN = re.compile(r"\b([a-z_]+)/([a-z_]+)\b")


def _doc() -> str:
    return DOC.read_text()


def _section(text: str, heading: str) -> str:
    """The text of the `## heading` section, up to the next heading of its level."""
    start = text.index(f"\n## {heading}")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else len(text)]


def _code_blocks(text: str) -> list[str]:
    return re.findall(r"```[^\n]*\n(.*?)```", text, re.S)


def _table_rows(text: str) -> Iterator[tuple[str, str]]:
    """(first cell, the rest) of each row of the markdown tables in `text`, header and rule left out."""
    for line in text.splitlines():
        match = re.match(r"\| (.+?) \| (.+) \|$", line)
        if match and not match[1].startswith("---") and "`" in match[1]:
            yield match[1], match[2]


def _units() -> set[str]:
    """Our package names as the doc writes dotted names: top-level packages and services' own."""
    return set(TOP) | {p.name for p in (ROOT / "services").iterdir() if _is_package(p)}


def _is_package(path: Path) -> bool:
    return path.is_dir() and path.name != "__pycache__" and any(path.glob("*.py"))


def packages() -> list[Path]:
    """Every package: the top-level ones, and each directory of Python modules under services/
    (a namespace package too)."""
    found = [ROOT / p for p in TOP if _is_package(ROOT / p)]
    found += [p for p in sorted((ROOT / "services").rglob("*")) if _is_package(p)]
    return found


def top_level_modules() -> list[Path]:
    return [p for p in sorted((ROOT / "services").glob("*.py")) if p.name != "__init__.py"]


# --- what the doc names --------------------------------------------------------------------------


def package_table_names() -> Iterator[tuple[str, Path | None]]:
    """(name as written, the path it names or None when nothing is there) for the backticked paths
    of the packages table."""
    for first, rest in _table_rows(_section(_doc(), "Packages and what each owns")):
        own = next((t for t in TICKED.findall(first) if PATHLIKE.fullmatch(t)), "")
        base = (ROOT / own).parent if own.endswith(".py") else ROOT / own  # the row's package
        for token in TICKED.findall(first) + TICKED.findall(rest):
            if PATHLIKE.fullmatch(token):
                yield token, _resolve(token, base)


def _resolve(token: str, base: Path) -> Path | None:
    """The path a backticked name of a row names: the row's package's, else the repository's."""
    for candidate in (base / token, ROOT / token):
        if candidate.exists():
            return candidate.resolve()
    return None


def rooted_paths(text: str) -> Iterator[tuple[str, Path | None]]:
    """Backticked paths from the top of the repository (`core/states.py`, `services/facts/`,
    `tests/test_layers.py`)."""
    for token in TICKED.findall(text):
        if PATHLIKE.fullmatch(token) and "/" in token.rstrip("/") and token.split("/")[0] in (*PACKAGES, "tests"):
            yield token, (ROOT / token).resolve() if (ROOT / token).exists() else None


def dotted_names(text: str) -> Iterator[str]:
    """Backticked `package.module.Name`s (first part one of our packages, as the doc writes them)."""
    units = _units() | {"services"}
    for token in TICKED.findall(text):
        if DOTTED.fullmatch(token) and token.split(".")[0] in units and not token.endswith(".py"):
            yield token


def drawn_modules(text: str) -> Iterator[str]:
    """`package/module` in the drawing of the data path (its first code block)."""
    units = _units()
    for package, module in DRAWN.findall(_code_blocks(text)[0]):
        if package in units:
            yield f"{package}/{module}"


def _module_file(dotted: str) -> Path | None:
    parts = dotted.split(".")
    if parts[0] not in TOP and parts[0] != "services":
        parts = ["services", *parts]
    path = ROOT.joinpath(*parts)
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return path if _is_package(path) else None


def _defines(module: Path, name: str) -> bool:
    """Whether the module defines `name` at its top level (a class, a function or an assignment)."""
    for node in ast.parse(module.read_text(), str(module)).body:
        if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef) and node.name == name:
            return True
        targets = [node.target] if isinstance(node, ast.AnnAssign) else getattr(node, "targets", [])
        if any(isinstance(t, ast.Name) and t.id == name for t in targets):
            return True
    return False


def missing_dotted(name: str) -> str | None:
    """Why a dotted name names nothing (None: it names a module, or what a module defines)."""
    if _module_file(name) is not None:
        return None
    module, _, attr = name.rpartition(".")
    found = _module_file(module)
    if found is None or found.is_dir():
        return f"`{name}`: no module {module}"
    if not _defines(found, attr):
        return f"`{name}`: {found.relative_to(ROOT)} defines no {attr}"
    return None


# --- the layer tables ----------------------------------------------------------------------------


def layer_table() -> list[set[str]]:
    """The doc's layers, lowest first."""
    block = _code_blocks(_section(_doc(), "The dependency rule"))[0]
    return parse_layers(block.splitlines())


def docstring_layers() -> list[set[str]]:
    """The layers the docstring of tests/test_layers.py draws: its lines indented by four spaces,
    the units before the description (deeper indented lines continue a description)."""
    assert LAYERS_DOC is not None
    lines = [line[4:] for line in LAYERS_DOC.splitlines() if re.match(r"    \S", line)]
    return parse_layers(re.split(r"\s{2,}", line)[0] for line in lines)


def parse_layers(lines: Iterable[str]) -> list[set[str]]:
    layers = []
    for line in lines:
        names = re.sub(r"\(.*?\)", "", line).strip()
        for layer in names.split("->") if names else ():
            layers.append({unit.strip() for unit in re.split(r"[,|]", layer) if unit.strip()})
    return layers


def expected_layers() -> list[set[str]]:
    """LAYERS of tests/test_layers.py as the doc writes units (without `services.`), lowest first;
    `services` itself (its `__init__` holds the version only) is left out."""
    by_layer: dict[int, set[str]] = {}
    for unit, layer in LAYERS.items():
        if unit != "services":
            by_layer.setdefault(layer, set()).add(unit.removeprefix("services."))
    return [by_layer[layer] for layer in sorted(by_layer)]


def layer_differences(drawn: list[set[str]], expected: list[set[str]]) -> list[str]:
    """What differs, layer by layer (lowest first), naming the units."""
    pairs = enumerate(zip(drawn, expected, strict=False))
    wrong = [f"layer {i}: draws {sorted(d)}, LAYERS has {sorted(e)}" for i, (d, e) in pairs if d != e]
    if len(drawn) != len(expected):
        wrong.append(f"{len(drawn)} layers drawn, LAYERS has {len(expected)}")
    return wrong


# --- the tests -----------------------------------------------------------------------------------


def test_every_path_the_doc_names_exists():
    text = _doc()
    gone = sorted({token for token, path in (*package_table_names(), *rooted_paths(text)) if path is None})
    gone += [
        f"{name} (drawn in the data path)"
        for name in drawn_modules(text)
        if _module_file(name.replace("/", ".")) is None
    ]
    assert not gone, f"{DOC.relative_to(ROOT)} names what is not in the tree: {gone}"


def test_every_dotted_name_the_doc_names_exists():
    wrong = sorted({why for name in dotted_names(_doc()) if (why := missing_dotted(name)) is not None})
    assert not wrong, f"{DOC.relative_to(ROOT)} names what is not in the tree:\n" + "\n".join(wrong)


def test_every_package_and_top_level_module_is_named():
    text = _doc()
    named = {path for _, path in (*package_table_names(), *rooted_paths(text)) if path is not None}
    unnamed = [p.relative_to(ROOT).as_posix() + "/" for p in packages() if p.resolve() not in named]
    unnamed += [p.relative_to(ROOT).as_posix() for p in top_level_modules() if p.resolve() not in named]
    assert not unnamed, f"give these a row (or a mention in their package's row) in {DOC.relative_to(ROOT)}: {unnamed}"


def test_the_doc_draws_the_layers_of_test_layers():
    wrong = layer_differences(layer_table(), expected_layers())
    assert not wrong, f"the layer table of {DOC.relative_to(ROOT)} is not tests/test_layers.py's:\n" + "\n".join(wrong)


def test_the_docstring_of_test_layers_draws_its_layers():
    wrong = layer_differences(docstring_layers(), expected_layers())
    assert not wrong, "the docstring of tests/test_layers.py is not its LAYERS:\n" + "\n".join(wrong)


def test_the_checks_name_what_is_wrong():
    assert missing_dotted("hot.read.HotRecording") is None
    assert missing_dotted("runs.indexed") is None
    assert (
        missing_dotted("hot.read.NoSuchThing") == "`hot.read.NoSuchThing`: services/hot/read.py defines no NoSuchThing"
    )
    assert missing_dotted("ingest.nowhere.Thing") == "`ingest.nowhere.Thing`: no module ingest.nowhere"
    assert parse_layers(["core", "auth | hot   (none imports another)", "server -> cli"]) == [
        {"core"},
        {"auth", "hot"},
        {"server"},
        {"cli"},
    ]
    assert layer_differences([{"core"}, {"hot"}], [{"core"}, {"hot", "facts"}]) == [
        "layer 1: draws ['hot'], LAYERS has ['facts', 'hot']"
    ]
    assert layer_differences([{"core"}], [{"core"}, {"hot"}]) == ["1 layers drawn, LAYERS has 2"]
