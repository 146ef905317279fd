"""A SQL worker: one query in a process of its own, then it exits.

The server starts it with the same interpreter and a scrubbed environment (no AWS_*, no FLEET_*, a
private HOME), so nothing DuckDB could read of its process reveals a credential or a server path.
It imports DuckDB while idle, then talks over stdin/stdout in length-prefixed frames:

    worker -> server  {}                                               (ready, after its imports)
    server -> worker  {"read_ahead": {"root", "s3", "files"}}  (optional, while idle: warming.py)
    server -> worker  {"query", "root", "layout", "limits", "s3", "hidden"}      (JSON)
    worker -> server  {"tables": [views the query names]} | {"error"}  (JSON; the query is checked)
    server -> worker  {"files": {table: [[file, ...], ...]}, "catalog": [name, ...]}, then one Arrow IPC
                      stream per catalog table
    worker -> server  {"rows": n} + the answer as Arrow IPC  |  {"error": {"code", "message"}}

Parsing, planning and running all happen here, so the server can stop any of them by killing the
process (time limit) and watch its resident memory (memory limit).
"""

from __future__ import annotations

import json
import os
import struct
import sys
import threading
from typing import IO, Any

_LENGTH = struct.Struct("!Q")


def write_frame(out: IO[bytes], data: bytes) -> None:
    out.write(_LENGTH.pack(len(data)))
    out.write(data)
    out.flush()


def read_frame(inp: IO[bytes]) -> bytes:
    head = inp.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        raise EOFError("the server closed the pipe")
    (size,) = _LENGTH.unpack(head)
    data = inp.read(size)
    if len(data) < size:
        raise EOFError("the server closed the pipe")
    return bytes(data)


def resident_bytes(pid: int | str = "self") -> int:
    """Resident memory of a process (Linux /proc; 0 where there is none)."""
    try:
        with open(f"/proc/{pid}/statm", "rb") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def main(argv: list[str]) -> int:
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but frames goes down the answer pipe
    import duckdb

    from core.errors import FleetError
    from services.analytics import sql, warming

    con = duckdb.connect(":memory:", config={"autoinstall_known_extensions": False, "autoload_known_extensions": False})
    if "--httpfs" in argv:  # while idle: a query does not wait for it
        con.execute(f"LOAD '{sql.httpfs_extension()}'")
    baseline = resident_bytes()
    write_frame(out, b"{}")  # ready: the server starts the query's clock now
    try:
        request = json.loads(read_frame(inp))
        if "read_ahead" in request:  # read while idle; the query stops it
            ahead = warming.ReadAhead(con, **request["read_ahead"])
            request = json.loads(read_frame(inp))
            ahead.stop()
    except EOFError:
        return 0  # the server stopped while this worker was idle
    scrub = sql.Scrubber(tuple(request["hidden"]))
    _exit_after(float(request["limits"]["seconds"]) + 10.0)
    try:
        answer = _serve(con, request, baseline, scrub, inp, out)
    except FleetError as exc:
        write_frame(out, json.dumps({"error": {"code": exc.code.value, "message": scrub.text(exc.message)}}).encode())
        return 0
    except EOFError:
        return 0
    except Exception as exc:  # one structured answer whatever failed
        message = scrub.text(f"the query failed: {sql.first_line(exc)}")
        write_frame(out, json.dumps({"error": {"code": "INTERNAL", "message": message}}).encode())
        return 0
    write_frame(out, json.dumps({"rows": answer.num_rows}).encode())
    write_frame(out, ipc_bytes(answer))
    return 0


def _serve(con: Any, request: dict[str, Any], baseline: int, scrub: Any, inp: IO[bytes], out: IO[bytes]) -> Any:
    import pyarrow as pa

    from services.analytics import sql

    limits = sql.Limits(**request["limits"])
    con.execute(f"SET threads = {int(limits.threads)}")
    con.execute(f"SET memory_limit = '{sql.duckdb_memory(limits, baseline)}B'")
    con.execute("SET temp_directory = ?", [os.path.join(os.getcwd(), f"spill-{os.getpid()}")])
    named = sql.check_query(con, request["query"])
    write_frame(out, json.dumps({"tables": sorted(named)}).encode())
    plan = json.loads(read_frame(inp))
    catalog = {name: pa.ipc.open_stream(read_frame(inp)).read_all() for name in plan["catalog"]}
    s3 = sql.S3Access(**request["s3"]) if request.get("s3") else None
    explain = sql.is_explain(con, request["query"])
    layout = request.get("layout", sql.PER_RUN)
    with sql.sandbox(con, request["root"], catalog, s3, plan["files"], layout) as sandboxed:
        answer = sql.run(sandboxed, request["query"], limits, limits.memory_bytes // 2)
    return scrub.table(answer) if explain else answer  # plans name the files read


def _exit_after(seconds: float) -> None:
    """The server kills a worker at the time limit; this covers a server that died first."""
    timer = threading.Timer(seconds, os._exit, [3])
    timer.daemon = True
    timer.start()


def ipc_bytes(table: Any) -> bytes:
    import pyarrow as pa

    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return bytes(sink.getvalue())


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
