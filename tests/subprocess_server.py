"""A server started as a subprocess for a test: `fleet serve`, SeaweedFS, ... One way to start it
with its environment and log, wait until it answers (or fail at once, with its log, if it exits),
and stop or kill it."""

from __future__ import annotations

import contextlib
import socket
import subprocess
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import httpx

from tests.waiting import wait_for

LOG_TAIL = 3000  # characters of the server's log quoted when it fails to start


def free_port() -> int:
    """A loopback port free right now (the OS picks it)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def answers_http(url: str, ok: Callable[[httpx.Response], bool] = lambda _: True) -> Callable[[], bool]:
    """A readiness check: `url` answers (and the answer passes `ok`)."""

    def check() -> bool:
        try:
            return ok(httpx.get(url, timeout=1))
        except httpx.TransportError:
            return False

    return check


class ServerProcess:
    """A command run as a server: its output goes to `log` (appended: a restarted server adds to
    it; its errors too unless `errors_log` is given), and `start` returns once `ready()` is true."""

    def __init__(
        self,
        argv: Sequence[str],
        *,
        log: Path,
        ready: Callable[[], bool],
        env: Mapping[str, str] | None = None,
        name: str | None = None,
        errors_log: Path | None = None,
    ) -> None:
        self.argv = list(argv)
        self.env = dict(env) if env is not None else None
        self.log = log
        self.errors_log = errors_log
        self.ready = ready
        self.name = name or Path(self.argv[0]).name
        self._proc: subprocess.Popen[bytes] | None = None

    @property
    def proc(self) -> subprocess.Popen[bytes]:
        if self._proc is None:
            raise AssertionError(f"{self.name} was not started")
        return self._proc

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self, timeout: float = 60) -> ServerProcess:
        """Start the command and wait until it is ready; fails if it exits first or the time runs out."""
        with contextlib.ExitStack() as files:  # the child holds its own descriptors
            log = files.enter_context(open(self.log, "ab"))
            errors = files.enter_context(open(self.errors_log, "ab")) if self.errors_log else subprocess.STDOUT
            self._proc = subprocess.Popen(self.argv, env=self.env, stdout=log, stderr=errors)
        try:
            self.wait_until(self.ready, timeout, "an answer")
        except BaseException:
            if self.running:  # one that never answered in time is not left running behind the failure
                self.kill()
            raise
        return self

    def wait_until(self, condition: Callable[[], bool], timeout: float, what: str) -> None:
        """Poll `condition` until it holds, while the process lives, within `timeout` seconds."""

        def living_and_holds() -> bool:
            if self.proc.poll() is not None:  # waiting longer is pointless: fail now, with its log
                raise AssertionError(
                    f"{self.name} exited with {self.proc.returncode} while waiting for {what}:\n{self.log_tail()}"
                )
            return condition()

        wait_for(living_and_holds, timeout, f"{what} from {self.name}", interval=0.05, detail=self.log_tail)

    def log_tail(self) -> str:
        return "\n".join(_tail(path) for path in (self.log, self.errors_log) if path is not None)

    def stop(self, grace: float = 30) -> None:
        """SIGTERM, then SIGKILL if it has not exited within `grace` seconds."""
        if not self.running:
            return
        self.proc.terminate()
        try:
            self.proc.wait(timeout=grace)
        except subprocess.TimeoutExpired:
            self.kill()

    def kill(self) -> None:
        """SIGKILL: no chance to clean up."""
        self.proc.kill()
        self.proc.wait(timeout=30)


def _tail(path: Path) -> str:
    try:
        return path.read_text(errors="replace")[-LOG_TAIL:]
    except OSError:
        return f"(no {path.name})"
