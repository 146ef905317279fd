"""The real Rerun viewer, headless, driven from a test the way a user would look at it.

`HeadlessViewer` starts `rerun --headless` on a free loopback port, with a home of its own (no
user state, stored credentials or analytics leak in or out) and Mesa's software Vulkan driver
(lavapipe), connects `rerun.experimental.ViewerClient`, opens URLs, and waits for what the viewer
shows by polling its observable state until a condition holds or the time runs out (no fixed
sleeps). What it observes:

- `ViewerClient.get_state()`: the location shown, the open recordings with their timelines, the
  views and their reports, and what is still loading;
- the servers the viewer knows, each with its entries (name, kind, URL) or its connection error:
  the `servers` field of the same viewer-control answer, which the SDK's `ViewerState` leaves out
  (read here from the answer itself);
- `get_table_schema()`, `get_recording_schema()`, `get_logs()`;
- the texts on screen (`tests.viewer_widgets`), for what only a table shows: its rows.

Screenshots are saved by the viewer under the test's folder; `assert_not_blank` checks one has content.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Generic, TypeVar

import numpy as np
from PIL import Image
from rerun.experimental import ViewerClient, ViewerState

from tests.subprocess_server import free_port
from tests.viewer_widgets import ViewerWidgets
from tests.waiting import wait_for

T = TypeVar("T")
V = TypeVar("V")

ICD_DIR = Path("/usr/share/vulkan/icd.d")
INSTALL_HINT = "apt-get install mesa-vulkan-drivers (Mesa's software Vulkan driver, lavapipe)"
# Variables of the developer's environment that would change what the viewer does or whom it talks
# to (a token, Rerun's own settings, where its state lives); a test passes what it needs in `env`.
LEAKY_VARIABLES = ("REDAP_TOKEN", "RERUN_", "XDG_", "RUST_LOG", "WGPU_", "VK_")
LOG_TAIL = 4000


class ViewerFailed(AssertionError):
    """The viewer reports a failure: no need to wait any longer."""


class NotYet(Exception):
    """Raised by a probe of `wait_until`: the condition does not hold yet, and what was seen instead."""


def lavapipe_icd() -> Path:
    """The ICD file of Mesa's software Vulkan driver, which the headless viewer renders with."""
    found = sorted(ICD_DIR.glob("lvp_icd.*.json"))
    if not found:
        raise AssertionError(f"no lvp_icd.*.json under {ICD_DIR}: {INSTALL_HINT}")
    return found[0]


def native_rerun(rerun_bin: str) -> str:
    """The `rerun` executable itself. The venv's `rerun` is a Python shim that runs it as a child
    and passes no signal on, so stopping the shim would leave the viewer running."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is None or spec.origin is None:
        return rerun_bin
    exe = Path(spec.origin).with_name("rerun")
    return str(exe) if exe.is_file() and os.access(exe, os.X_OK) else rerun_bin


# --- what the viewer shows ------------------------------------------------------------------------


@dataclass(frozen=True)
class Entry:
    """An entry a server lists: a dataset or a table."""

    name: str
    kind: str  # "ENTRY_KIND_DATASET", ...
    url: str  # rerun+http://HOST:PORT/entry/ID

    @property
    def id(self) -> str:
        return self.url.rsplit("/", 1)[1]

    @property
    def origin(self) -> str:
        return self.url.rsplit("/entry/", 1)[0]

    @property
    def dataset_url(self) -> str:
        """The dataset page: its segment table."""
        return f"{self.origin}/dataset/{self.id}"

    def segment_url(self, segment_id: str) -> str:
        return f"{self.dataset_url}?segment_id={segment_id}"


@dataclass(frozen=True)
class Server:
    origin: str
    entries: list[Entry]
    error: str | None  # why the viewer could not use it, as it tells the user


@dataclass(frozen=True)
class Snapshot:
    state: ViewerState
    servers: list[Server]

    def server(self, origin: str) -> Server | None:
        return next((s for s in self.servers if s.origin == origin.rstrip("/")), None)

    def recording(self, segment_id: str) -> Any | None:
        """The open recording of this recording (or segment) id, or None."""
        return next((r for r in self.state.recordings if recording_id(r.store_id) == segment_id), None)


def recording_id(store_id: str) -> str:
    """The recording id of a viewer store id `KIND:APPLICATION:RECORDING`, where the application id
    has its colons escaped as `\\:` (and backslashes as `\\\\`)."""
    _, _, rest = store_id.partition(":")
    i = 0
    while i < len(rest):
        if rest[i] == "\\":
            i += 2
            continue
        if rest[i] == ":":
            return rest[i + 1 :]
        i += 1
    return ""


def _servers(raw: dict[str, Any]) -> list[Server]:
    return [
        Server(
            origin=s.get("origin", ""),
            entries=[Entry(e.get("name", ""), e.get("kind", ""), e.get("url", "")) for e in s.get("entries", [])],
            error=s.get("error"),
        )
        for s in raw.get("servers", [])
    ]


@dataclass(frozen=True)
class Waited(Generic[V]):
    value: V
    seconds: float  # how long the condition took to hold


# --- the viewer process -----------------------------------------------------------------------------


class HeadlessViewer:
    """`rerun --headless` on a free loopback port, its files (home, log, screenshots) in `workdir`.

    `env` adds variables (e.g. REDAP_TOKEN); `connect` starts it on `--connect URL` (a message
    proxy). Use as a context manager, or `start()` and `stop()`."""

    def __init__(
        self,
        rerun_bin: str,
        workdir: Path,
        *,
        env: Mapping[str, str] | None = None,
        connect: str | None = None,
        window: tuple[int, int] = (1280, 800),
    ) -> None:
        self.exe = native_rerun(rerun_bin)
        self.workdir = workdir
        self.port = free_port()
        self.log = workdir / "viewer.log"
        self.screenshots = workdir / "screenshots"
        self.env = self._environment(env or {})
        size = f"{window[0]}x{window[1]}"
        self.argv = [self.exe, "--headless", "--hide-welcome-screen", "--bind", "127.0.0.1", "--port", str(self.port)]
        self.argv += ["--window-size", size, *(["--connect", connect] if connect else [])]
        self._proc: subprocess.Popen[bytes] | None = None
        self._client: ViewerClient | None = None
        self._widgets: ViewerWidgets | None = None

    def _environment(self, extra: Mapping[str, str]) -> dict[str, str]:
        home = self.workdir / "home"
        home.mkdir(parents=True, exist_ok=True)
        base = {k: v for k, v in os.environ.items() if not k.startswith(LEAKY_VARIABLES)}
        return {**base, "HOME": str(home), "VK_ICD_FILENAMES": str(lavapipe_icd()), **extra}

    @property
    def url(self) -> str:
        """The viewer's own message proxy, what ViewerClient connects to."""
        return f"rerun+http://127.0.0.1:{self.port}/proxy"

    @property
    def client(self) -> ViewerClient:
        if self._client is None:
            raise AssertionError("the viewer was not started")
        return self._client

    def start(self, timeout: float = 60) -> HeadlessViewer:
        self.screenshots.mkdir(parents=True, exist_ok=True)
        # Analytics off in this home before the viewer first runs, the way a user turns them off.
        subprocess.run([self.exe, "analytics", "disable"], env=self.env, capture_output=True, timeout=60, check=True)
        with open(self.log, "ab") as log:
            # Its own process group: stopping it stops whatever it spawned too.
            self._proc = subprocess.Popen(
                self.argv, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        try:
            self.wait_until(self._listening, "the viewer's port to open", timeout)
            self._client = ViewerClient.connect(self.url)
            self.wait_until(self._answers, "the viewer's first answer", timeout)
        except BaseException:
            self.stop()
            raise
        return self

    def _listening(self) -> bool:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port), timeout=1):
            return True
        return False

    def _answers(self) -> bool:
        with contextlib.suppress(ConnectionError):
            return self.client.get_state() is not None
        return False

    def stop(self) -> None:
        if self._widgets is not None:
            self._widgets.stop()
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=15)

    def __enter__(self) -> HeadlessViewer:
        return self if self._proc is not None else self.start()

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.stop()

    @property
    def widgets(self) -> ViewerWidgets:
        """The texts on screen, through `rerun viewer-mcp` (started on first use)."""
        if self._widgets is None:
            endpoint = f"http://127.0.0.1:{self.port}"
            self._widgets = ViewerWidgets(self.exe, endpoint, env=self.env, log=self.workdir / "viewer-mcp.log")
            self._widgets.start()
        return self._widgets

    # --- observing -----------------------------------------------------------------------------------

    def snapshot(self) -> Snapshot:
        raw = self.client._viewer_control("get_state", {})  # the SDK's ViewerState drops `servers`
        return Snapshot(self.client.get_state(), _servers(raw))

    def last_log(self) -> int:
        """The sequence number of the viewer's newest log message (0 for none)."""
        return max((entry.sequence for entry in self.client.get_logs()), default=0)

    def errors(self, after: int = 0) -> list[str]:
        """The viewer's ERROR messages logged after sequence `after`."""
        return [entry.message for entry in self.client.get_logs(after) if entry.level == "ERROR"]

    def wait_until(self, probe: Callable[[], T | None], what: str, timeout: float = 30) -> Waited[T]:
        """Poll `probe` until it returns something truthy (its value is returned, with how long it
        took), while the viewer lives; fails with what the viewer shows after `timeout` seconds.
        A probe raises NotYet to say what it saw instead."""

        def living_probe() -> T | None:
            if self._proc is None or self._proc.poll() is not None:  # waiting longer is pointless
                raise AssertionError(f"the viewer is not running while waiting for {what}:\n{self.log_tail()}")
            return probe()

        started = time.monotonic()
        value = wait_for(living_probe, timeout, what, tolerate=(NotYet,), detail=self.describe)
        return Waited(value, time.monotonic() - started)

    def describe(self) -> str:
        """What the viewer shows and said, for a failure message."""
        if self._client is None:
            return self.log_tail()
        with contextlib.suppress(ConnectionError):
            logs = [f"{e.level} {e.target}: {e.message[:500]}" for e in self.client.get_logs() if e.level != "INFO"]
            return f"state: {self.snapshot()}\nviewer log:\n" + "\n".join(logs[-20:])
        return self.log_tail()

    def log_tail(self) -> str:
        try:
            return self.log.read_text(errors="replace")[-LOG_TAIL:]
        except OSError:
            return "(no viewer log)"

    # --- ready-made conditions -----------------------------------------------------------------------

    def open(self, url: str) -> int:
        """Open `url`; the log sequence it was opened at, for `errors(after)`."""
        mark = self.last_log()
        self.client.open(url)
        return mark

    def wait_for_entries(self, origin: str, names: set[str], timeout: float = 30) -> Waited[dict[str, Entry]]:
        """The entries of the server at `origin` once it lists every name in `names`; fails at once
        if the viewer reports an error for that server."""

        def listed() -> dict[str, Entry] | None:
            server = self.snapshot().server(origin)
            if server is not None and server.error:
                raise ViewerFailed(f"the viewer could not use {origin}: {server.error}")
            entries = {e.name: e for e in server.entries} if server else {}
            return entries if names <= entries.keys() else None

        return self.wait_until(listed, f"{origin} to list {sorted(names)}", timeout)

    def wait_for_texts(
        self, pane: str, holds: Callable[[list[str]], bool], what: str, timeout: float = 30
    ) -> Waited[list[str]]:
        """The texts shown in the pane labelled `pane` (e.g. "Server page") once `holds(texts)`."""

        def shown() -> list[str]:
            on_screen = self.widgets.texts(pane)
            if not holds(on_screen):
                raise NotYet(f"{pane!r} shows {on_screen}")
            return on_screen

        return self.wait_until(shown, f"{what} shown in the {pane!r} pane", timeout)

    def wait_for_recording(self, segment_id: str, opened_at: int = 0, timeout: float = 30) -> Waited[Any]:
        """The open recording of `segment_id` once it is active and fully loaded (nothing loading,
        every timeline with a range); fails at once on a "Data source failed" error."""

        def loaded() -> Any | None:
            failed = [e for e in self.errors(opened_at) if "Data source failed" in e]
            if failed:
                raise ViewerFailed(f"the viewer could not load {segment_id}: {failed[0]}")
            snap = self.snapshot()
            recording = snap.recording(segment_id)
            if recording is None or snap.state.active_recording != recording.store_id or snap.state.loading:
                return None
            ranged = recording.timelines and all(t.end is not None for t in recording.timelines)
            return recording if ranged else None

        return self.wait_until(loaded, f"recording {segment_id} loaded", timeout)

    def screenshot(self, name: str, view_id: str | None = None) -> Path:
        """The whole viewer (or one view) as `screenshots/NAME.png`, saved by the viewer once it has painted."""
        path = self.screenshots / f"{name}.png"
        self.client.save_screenshot(str(path.resolve()), view_id=view_id)
        if not path.is_file():
            raise AssertionError(f"the viewer saved no screenshot at {path}")
        return path


# --- screenshots ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImageStats:
    width: int
    height: int
    colours: int  # distinct colours
    foreground: float  # share of pixels not of the most common colour (the background)
    chromatic: float  # share of clearly coloured pixels (data, not the viewer's grey UI)


def _pixels(path: Path) -> np.ndarray[Any, np.dtype[np.int16]]:
    with Image.open(path) as image:
        return np.asarray(image.convert("RGB"), dtype=np.int16)


def image_stats(path: Path) -> ImageStats:
    pixels = _pixels(path)
    flat = pixels.reshape(-1, 3)
    _, counts = np.unique(flat, axis=0, return_counts=True)
    spread = pixels.max(axis=2) - pixels.min(axis=2)
    return ImageStats(
        width=pixels.shape[1],
        height=pixels.shape[0],
        colours=len(counts),
        foreground=float(1 - counts.max() / len(flat)),
        chromatic=float((spread > 64).mean()),
    )


def changed_share(before: Path, after: Path, tolerance: int = 24) -> float:
    """The share of pixels that differ (by more than `tolerance` in a channel) between two
    screenshots of the same size."""
    a, b = _pixels(before), _pixels(after)
    if a.shape != b.shape:
        return 1.0
    return float((np.abs(a - b).max(axis=2) > tolerance).mean())


def assert_not_blank(path: Path, *, min_colours: int = 32, min_foreground: float = 0.01) -> ImageStats:
    """A screenshot with content: enough distinct colours and enough pixels off the background."""
    stats = image_stats(path)
    assert stats.colours >= min_colours and stats.foreground >= min_foreground, f"{path} looks blank: {stats}"
    return stats
