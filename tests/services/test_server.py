"""What `fleet serve` loads before it serves: every start pays for it (a deployment's restarts, each
of `--workers N`, the suite's hundreds of servers), so parts that only some requests use (the
lakehouse's pyiceberg, the MCP SDK) are loaded by the first request that needs them."""

from __future__ import annotations

import json
import subprocess
import sys

ON_FIRST_USE = ("pyiceberg", "mcp")


def test_the_server_loads_the_lakehouse_and_mcp_only_when_used() -> None:
    probe = (
        "import json, sys, services.server; "
        f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({ON_FIRST_USE!r}))))"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(done.stdout) == []


# What a run's first window or manifest after a start would otherwise import on first use.
FIRST_WINDOW_IMPORTS = ("numpy.ma", "pyarrow.dataset")


def test_the_server_warms_up_what_a_first_window_would_load() -> None:
    probe = (
        "import json, sys, services.server; before = set(sys.modules); services.server.warm_up(); "
        f"print(json.dumps(sorted((set(sys.modules) - before) & set({FIRST_WINDOW_IMPORTS!r}))))"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(done.stdout) == sorted(FIRST_WINDOW_IMPORTS)
