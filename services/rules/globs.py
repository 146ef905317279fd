"""Entity path globs of the rules: `/a/b` that entity, `*` one segment (or part of one), `**` any
number of segments (none too: `/logs/**` is `/logs` and everything under it).

Compiled once per rule, to re2 (linear time, whatever the pattern), and matched once per entity
path by the rule set's cache (`spec.RuleSet.rules_for`)."""

from __future__ import annotations

import re
from typing import Any

import re2

MAX_ENTITY_LENGTH = 1024


def is_glob(entity: str) -> bool:
    return "*" in entity


def entity_problem(entity: str) -> str | None:
    """Why `entity` is no entity path or glob (None: it is one)."""
    if len(entity) > MAX_ENTITY_LENGTH:  # first: the messages below quote the path
        return f"an entity path of {len(entity)} characters: at most {MAX_ENTITY_LENGTH}"
    if not entity.startswith("/"):
        return f"{entity!r} is not an entity path: it starts with '/' (e.g. /world/robot or /logs/**)"
    segments = entity[1:].split("/") if entity != "/" else []
    if any(not s for s in segments):
        return f"{entity!r} has an empty segment ('//' or a trailing '/')"
    if any("**" in s and s != "**" for s in segments):
        return f"{entity!r}: '**' stands for whole segments only (/a/**/b), not part of one"
    return None


def compile_glob(entity: str) -> Any:
    """The re2 pattern of a glob (checked by `entity_problem` first)."""
    parts = []
    for segment in entity[1:].split("/"):
        if segment == "**":
            parts.append("(?:/[^/]+)*")
        else:
            parts.append("/" + "[^/]*".join(re.escape(piece) for piece in segment.split("*")))
    return re2.compile("".join(parts))


def matches(pattern: Any, path: str) -> bool:
    return pattern.fullmatch(path) is not None
