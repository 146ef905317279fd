"""Which Rerun clients the catalog server answers: the protocol changes every Rerun release under
the same `v1alpha1` name, so a client outside the tested range is told so, clearly, rather than
failing somewhere deep in its own code. docs/catalog-server.md says how to add a release."""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

from core.errors import ConflictError, InvalidArgumentError

CLIENT_VERSION_HEADER = "x-rerun-client-version"
# The tested range (inclusive), as (major, minor): see tests/services/redap and docs/catalog-server.md.
OLDEST = (0, 36)
NEWEST = (0, 41)
_VERSION = re.compile(r"^(?P<client>[\w.-]+)/(?P<major>\d+)\.(?P<minor>\d+)")
_MAX_DIGITS = 9  # a version number no release has; Python refuses to read an int of over 4,300 digits


def check_client(metadata: Iterable[tuple[str, Any]] | None) -> None:
    """FAILED_PRECONDITION for a Rerun client outside the tested range, naming the range; a call
    without the header (not a Rerun client, or a tool) is let through."""
    for key, value in metadata or ():
        if key != CLIENT_VERSION_HEADER:
            continue
        found = _VERSION.match(value.decode() if isinstance(value, bytes) else str(value))
        if found is None:
            return
        if max(len(found["major"]), len(found["minor"])) > _MAX_DIGITS:
            raise InvalidArgumentError(f"the {CLIENT_VERSION_HEADER} header is malformed: send the client's own")
        version = (int(found["major"]), int(found["minor"]))
        if not OLDEST <= version <= NEWEST:
            raise ConflictError(
                f"{found['client']} {version[0]}.{version[1]} is outside the Rerun versions this depot's catalog "
                f"serves ({OLDEST[0]}.{OLDEST[1]} to {NEWEST[0]}.{NEWEST[1]}): use rerun-sdk=={NEWEST[0]}.{NEWEST[1]}.*"
            )
