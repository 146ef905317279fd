"""Rerun's entity path patterns as clients give them (`/world/**` the subtree, anything else the
exact path), checked once: by downloads, which apply them, and by pulls, which a robot's agent applies."""

from __future__ import annotations

from collections.abc import Sequence

from core.errors import BadParameterError

MAX_PATTERNS = 256  # include and exclude patterns each: matching stays cheap, whatever a client sends
MAX_PATTERN_LENGTH = 1024


def check_entity_patterns(name: str, patterns: Sequence[str]) -> None:
    """Refuse (naming the parameter `name` and the fix) too many patterns, a pattern too long, or
    one that is no entity path pattern."""
    if len(patterns) > MAX_PATTERNS:
        raise BadParameterError(
            name,
            f"{len(patterns)} patterns: at most {MAX_PATTERNS}; use a subtree "
            "pattern like /a/** to cover many entities",
        )
    for pattern in patterns:
        if len(pattern) > MAX_PATTERN_LENGTH:
            raise BadParameterError(name, f"a pattern of {len(pattern)} characters: at most {MAX_PATTERN_LENGTH}")
        if not pattern.startswith("/") or "**" in pattern[:-2]:
            raise BadParameterError(
                name, f"{pattern!r} is not an entity path pattern: use /a/b (that entity) or /a/** (the subtree)"
            )
