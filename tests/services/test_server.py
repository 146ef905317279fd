"""What `fleet serve` loads before it serves: every start pays for it (a deployment's restarts, each
of `--workers N`, the suite's hundreds of servers), so parts that only some requests use (the
lakehouse's pyiceberg, the MCP SDK) are loaded by the first request that needs them, while what a
run's first window or manifest would load is loaded by the server's warm-up."""

from __future__ import annotations

import json
import subprocess
import sys

ON_FIRST_USE = ("pyiceberg", "mcp")
# What a run's first window or manifest after a start would otherwise import on first use.
FIRST_WINDOW_IMPORTS = ("numpy.ma", "pyarrow.dataset")


def loaded(script: str, names: tuple[str, ...]) -> list[str]:
    """Which of `names` (modules, or packages with any module loaded) a fresh interpreter that
    imported the server's modules has loaded after `script`."""
    probe = (
        f"import json, sys, services.server; {script}; "
        "found = set(sys.modules) | {m.split('.')[0] for m in sys.modules}; "
        f"print(json.dumps(sorted(found & set({names!r}))))"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    found: list[str] = json.loads(done.stdout)
    return found


def test_the_server_loads_the_lakehouse_and_mcp_only_when_used() -> None:
    assert loaded("pass", ON_FIRST_USE) == []


def test_the_server_warms_up_what_a_first_window_would_load() -> None:
    assert loaded("pass", FIRST_WINDOW_IMPORTS) == []  # not imported with the server's modules
    assert loaded("services.server.warm_up()", FIRST_WINDOW_IMPORTS) == sorted(FIRST_WINDOW_IMPORTS)
