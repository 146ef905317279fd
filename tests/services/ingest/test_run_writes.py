"""Only ingest writes a hot run: no module that may import ingest assigns a field of an `IngestRun`.

Other services get `HotRunView`s (frozen) and ask ingest to change a run (`hand_over`, `take_lease`,
`lose_lease`, `set_adds_to`); this test keeps it so by reading the source. Without types, any
assignment to an attribute named like a run's field counts (`x.status = ...`, `x.lease += ...`,
`x.chunk_ids[k] = ...`), except to the assigning object's own (`self.`, `cls.`); an object that is not
a run but has such a field goes into ALLOWED with what it is. Lower layers than ingest cannot import
it (tests/test_layers.py), so only the layers above it are read.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

from tests.test_layers import LAYERS, ROOT, module_of, unit_of

RUN_CLASSES = (("services/ingest/run.py", "IngestRun"), ("services/facts/run.py", "RunFacts"))

# (file, assignment target) -> what the object is: not a hot run.
ALLOWED = {
    ("services/retention/scrub.py", "objects[RECORDING].size"): "a catalog ObjectRecord",
    ("services/retention/scrub.py", "objects[INDEX].size"): "a catalog ObjectRecord",
    ("services/agent/files.py", "p.size"): "a watched file's progress",
}


def run_fields() -> set[str]:
    """The instance attributes the run classes set in their `__init__`."""
    fields = set()
    for path, name in RUN_CLASSES:
        tree = ast.parse((ROOT / path).read_text(), path)
        (cls,) = [node for node in ast.walk(tree) if isinstance(node, ast.ClassDef) and node.name == name]
        (init,) = [node for node in cls.body if isinstance(node, ast.FunctionDef) and node.name == "__init__"]
        for node in ast.walk(init):
            for target in _targets(node):
                if isinstance(target, ast.Attribute) and _is_own(target):
                    fields.add(target.attr)
    return fields


def _targets(node: ast.AST) -> Iterator[ast.expr]:
    """What an assignment writes, tuples unpacked (`a.x, b.y = ...`)."""
    if isinstance(node, ast.Assign):
        pending = list(node.targets)
    elif isinstance(node, ast.AugAssign | ast.AnnAssign):
        pending = [node.target]
    else:
        return
    while pending:
        target = pending.pop()
        if isinstance(target, ast.Tuple | ast.List):
            pending += target.elts
        elif isinstance(target, ast.Starred):
            pending.append(target.value)
        else:
            yield target


def _is_own(target: ast.Attribute) -> bool:
    return isinstance(target.value, ast.Name) and target.value.id in ("self", "cls")


def run_writes(source: str, filename: str, fields: set[str]) -> list[tuple[int, str]]:
    """(line, target) of each assignment in `source` to a run field of an object not its own."""
    found = []
    for node in ast.walk(ast.parse(source, filename)):
        for target in _targets(node):
            written = target.value if isinstance(target, ast.Subscript) else target  # x.field[k] = ...
            if isinstance(written, ast.Attribute) and written.attr in fields and not _is_own(written):
                found.append((target.lineno, ast.unparse(target if written is target else written)))
    return found


def modules_above_ingest() -> Iterator[Path]:
    above = LAYERS["services.ingest"]
    for path in sorted((ROOT / "services").rglob("*.py")):
        if LAYERS[unit_of(module_of(path))] > above:
            yield path


def test_no_module_outside_ingest_writes_a_run():
    fields = run_fields()
    seen, wrong = set(), []
    for path in modules_above_ingest():
        rel = path.relative_to(ROOT).as_posix()
        for line, target in run_writes(path.read_text(), rel, fields):
            if (rel, target) in ALLOWED:
                seen.add((rel, target))
            else:
                wrong.append(f"{rel}:{line}: assigns {target}, a field of a hot run: ask ingest to change it")
    assert not wrong, "\n".join(wrong)
    assert seen == set(ALLOWED), f"no longer written, take out of ALLOWED: {sorted(set(ALLOWED) - seen)}"


def test_the_check_knows_the_run_fields_and_catches_a_write():
    fields = run_fields()
    assert {"status", "lease", "handed_over", "adds_to", "sealed_to", "chunk_ids", "dirty"} <= fields
    sample = "def f(run, runs):\n    run.lease = None\n    runs[0].handed_over, n = True, 1\n    run.size += 1\n"
    sample += "    run.chunk_ids[k] = 1\n    self.status = 'mine'\n    run.other = 1\n"
    assert run_writes(sample, "sample.py", fields) == [
        (2, "run.lease"),
        (3, "runs[0].handed_over"),
        (4, "run.size"),
        (5, "run.chunk_ids"),
    ]
    assert any(path.match("services/retention/promote.py") for path in modules_above_ingest())
    assert not any(path.match("services/ingest/*.py") for path in modules_above_ingest())
