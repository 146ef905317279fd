"""What `fleet` loads before it runs a command: every command line pays for it (a robot's upload,
an engineer's `runs ls`, a script calling the CLI in a loop), so the depot's heavy parts (the RRD
codec and pyarrow, the catalog's SQLAlchemy, DuckDB, gRPC, Rerun) are loaded only by the commands
that use them."""

from __future__ import annotations

import json
import subprocess
import sys

from services.cli.rrd import DEFAULT_MAX_MESSAGE_SIZE
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE as DECODERS_DEFAULT

HEAVY = ("pyarrow", "numpy", "sqlalchemy", "duckdb", "grpc", "rerun", "fastapi", "uvicorn")


def test_the_command_line_loads_none_of_the_heavy_parts_to_start() -> None:
    probe = f"import json, sys, services.cli.main; print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(done.stdout) == []


def test_rrd_inspects_default_limit_is_the_decoders() -> None:
    assert DEFAULT_MAX_MESSAGE_SIZE == DECODERS_DEFAULT
