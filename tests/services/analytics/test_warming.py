"""An idle SQL worker's read-ahead (services/analytics/warming.py) and how the pool hands it out.

The read-ahead is measured where it matters, in the requests a query then sends: against a loopback
HTTP file server that counts them, a query after the read-ahead sends no HEAD and reads no footer
again. A read-ahead stuck on a store that does not answer lets the query go within a moment; the
pool plans read-aheads for the tables the last query read, and never sends one to a worker a query
has taken (it would arrive in the middle of the query's conversation)."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from services.analytics import sql, warming
from services.analytics.pool import Prepared, SqlPool
from tests.waiting import wait_for

FILES = 6
ROWS = 1000


class FileServer:
    """Serves a folder over HTTP/1.1 with HEAD and ranged GET, counting requests per method; paths
    under /stall/ answer only once `release` is set."""

    def __init__(self, root: Path) -> None:
        self.requests: collections.Counter[str] = collections.Counter()
        self.release = threading.Event()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args: Any) -> None:
                pass

            def _file(self) -> bytes | None:
                server.requests[self.command] += 1
                if self.path.startswith("/stall/"):
                    server.release.wait(30)
                found = root / self.path.rsplit("/", 1)[-1]
                if not found.is_file():
                    self.send_response(404)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return None
                return found.read_bytes()

            def do_HEAD(self) -> None:
                data = self._file()
                if data is not None:
                    self.send_response(200)
                    self.send_header("Content-Length", str(len(data)))
                    self.send_header("Accept-Ranges", "bytes")
                    self.send_header("Last-Modified", "Tue, 01 Dec 2026 00:00:00 GMT")
                    self.end_headers()

            def do_GET(self) -> None:
                data = self._file()
                if data is None:
                    return
                first, last = 0, len(data) - 1
                ranged = self.headers.get("Range", "")
                if ranged.startswith("bytes="):
                    low, _, high = ranged.removeprefix("bytes=").partition("-")
                    first, last = int(low), min(int(high or last), last)
                self.send_response(206 if ranged else 200)
                self.send_header("Content-Length", str(last - first + 1))
                if ranged:
                    self.send_header("Content-Range", f"bytes {first}-{last}/{len(data)}")
                self.end_headers()
                self.wfile.write(data[first : last + 1])

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.release.set()
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def files(tmp_path: Path) -> Iterator[tuple[FileServer, list[str]]]:
    for i in range(FILES):
        table = pa.table({"run_id": [f"run-{i}"] * ROWS, "value": [float(v) for v in range(ROWS)]})
        pq.write_table(table, tmp_path / f"part-{i}.parquet")
    server = FileServer(tmp_path)
    try:
        yield server, [f"{server.url}/data/part-{i}.parquet" for i in range(FILES)]
    finally:
        server.close()


def database() -> duckdb.DuckDBPyConnection:
    con = duckdb.connect(":memory:", config={"autoinstall_known_extensions": False, "autoload_known_extensions": False})
    con.execute(f"LOAD '{sql.httpfs_extension()}'")
    sql.cache_settings(con)
    return con


def query(con: duckdb.DuckDBPyConnection, urls: list[str]) -> Any:
    return con.execute(f"SELECT count(*), sum(value) FROM read_parquet([{sql.listed(urls)}])").fetchone()


def test_after_a_read_ahead_a_query_sends_no_head_and_reads_no_footer_again(files: tuple[FileServer, list[str]]):
    server, urls = files
    cold = database()
    answer = query(cold, urls)
    cold_requests = dict(server.requests)
    assert answer == (FILES * ROWS, FILES * sum(range(ROWS)))
    assert cold_requests.get("HEAD", 0) >= FILES, cold_requests  # each file's size, asked of the store

    warm = database()
    ahead = warming.ReadAhead(warm, "http://", None, urls)
    wait_for(lambda: ahead.done, 30, "the read-ahead to finish")
    server.requests.clear()
    assert query(warm, urls) == answer
    warm_requests = dict(server.requests)
    assert warm_requests.get("HEAD", 0) == 0, warm_requests
    # the footers were parsed ahead: only the data is read now
    assert warm_requests.get("GET", 0) < cold_requests["GET"], (warm_requests, cold_requests)


def test_a_read_ahead_stuck_on_the_store_lets_the_query_go(files: tuple[FileServer, list[str]], tmp_path: Path):
    server, urls = files
    con = database()
    ahead = warming.ReadAhead(con, "http://", None, [url.replace("/data/", "/stall/") for url in urls])
    wait_for(lambda: server.requests["HEAD"] >= 1, 30, "the read-ahead to ask the store")
    started = time.monotonic()
    ahead.stop()
    assert time.monotonic() - started < warming.STOP_WAIT_S + 0.5
    local = str(tmp_path / "part-0.parquet")
    assert con.execute(f"SELECT count(*) FROM read_parquet('{local}')").fetchone() == (ROWS,)
    server.release.set()


def test_a_read_ahead_of_files_that_are_gone_changes_no_answer(files: tuple[FileServer, list[str]]):
    server, urls = files
    con = database()
    ahead = warming.ReadAhead(con, "http://", None, [f"{server.url}/data/missing.parquet", *urls])
    wait_for(lambda: ahead.done, 30, "the read-ahead to give up")
    assert query(con, urls) == (FILES * ROWS, FILES * sum(range(ROWS)))


# --- the pool: what it reads ahead, and when it must not send it --------------------------------


def partition(tmp_path: Path, count: int) -> list[str]:
    """`count` files of ROWS values each, where the analytics views look for them."""
    folder = tmp_path / "robot_id=robot-1" / "date=2026-03-01"
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        pq.write_table(pa.table({"value": [float(v) for v in range(ROWS)]}), folder / f"run-{i}.parquet")
    return [str(folder / f"run-{i}.parquet") for i in range(count)]


def per_run_request(tmp_path: Path, text: str) -> dict[str, Any]:
    return {"query": text, "root": str(tmp_path), "layout": sql.PER_RUN, "s3": None, "hidden": [str(tmp_path)]}


def test_idle_workers_read_ahead_the_tables_the_last_query_read(files: tuple[FileServer, list[str]], tmp_path: Path):
    server, urls = files
    local = [partition(tmp_path / "tables", FILES)]
    planned: list[tuple[str, ...]] = []

    def plan(tables: tuple[str, ...]) -> dict[str, Any]:
        planned.append(tables)
        return {"root": "http://", "s3": None, "files": urls}

    pool = SqlPool(sql.Limits(workers=1), httpfs=True, read_ahead=plan)
    try:
        pool.start()
        assert pool.submit(per_run_request(tmp_path, "SELECT 1 AS one"), lambda _: Prepared()).result(60).num_rows == 1
        assert planned == []  # no analytics table read yet: nothing to read ahead

        def prepare(named: set[str]) -> Prepared:
            return Prepared(files={"scalars": local} if "scalars" in named else {})

        text = "SELECT count(*) AS n FROM scalars"
        first = pool.submit(per_run_request(tmp_path, text), prepare).result(60)
        wait_for(lambda: planned == [("scalars",)], 30, "a read-ahead of scalars for the next worker")
        pool._planner.submit(lambda: None).result(30)  # the frame is sent
        wait_for(lambda: server.requests["HEAD"] >= FILES, 30, "the idle worker to read the footers ahead")
        second = pool.submit(per_run_request(tmp_path, text), prepare).result(60)
        assert first.to_pylist() == second.to_pylist() == [{"n": FILES * ROWS}]
    finally:
        pool.close()


def test_a_read_ahead_planned_after_a_query_took_the_worker_is_not_sent(tmp_path: Path):
    """The plan comes back while the query talks to the worker (between its tables and its files):
    sent then, the worker would read it as the query's files."""
    (path,) = partition(tmp_path, 1)
    planning, planned = threading.Event(), threading.Event()

    def plan(_: tuple[str, ...]) -> dict[str, Any]:
        planning.wait(30)
        planned.set()
        return {"root": str(tmp_path), "s3": None, "files": [path]}

    pool = SqlPool(sql.Limits(workers=1), httpfs=False, read_ahead=plan)
    prepared: list[set[str]] = []

    def prepare(named: set[str]) -> Prepared:
        prepared.append(named)
        if len(prepared) == 2:  # the second query, on the worker whose plan waits: let it through
            planning.set()
            pool._planner.submit(lambda: None).result(30)  # its frame was sent, or not
        return Prepared(files={"scalars": [[path]]})

    try:
        text = "SELECT count(*) AS n FROM scalars"
        assert pool.submit(per_run_request(tmp_path, text), prepare).result(60).to_pylist() == [{"n": ROWS}]
        assert not planning.is_set()  # the next worker's plan waits
        assert pool.submit(per_run_request(tmp_path, text), prepare).result(60).to_pylist() == [{"n": ROWS}]
        assert planned.is_set()
    finally:
        planning.set()
        pool.close()
