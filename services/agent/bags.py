"""Finding the MCAP files robots record (rosbag2 bags, or lone `.mcap` files) in the watched folders,
and deciding when each is closed, so that the agent uploads it whole and once.

A file is closed when its writer says so: it ends with MCAP's trailing magic (the writer wrote the
footer) and either its rosbag2 folder's `metadata.yaml` lists it, or a later split of the same bag
exists. Neither sign is enough alone: rosbag2 writes `metadata.yaml` before it closes the last file,
and opens split N+1 before it closes split N, so either may be seen while the footer is still being
written; and a lone file with the magic may be rewritten by a tool that writes in place. Failing
that, a file is closed once its size, mtime and inode stayed the same for `idle_s` (a recorder that
crashed leaves a file without footer that never changes; a copier that finished, likewise).

`BagScanner.scan` does the blocking work (a walk, stats, reading `metadata.yaml` and a file's first
and last bytes): the agent runs it on a worker thread. Its clock is injectable, so the idle rule is
tested without sleeping.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from core.ids import ID_LENGTH, SAFE_ID

log = logging.getLogger("fleet.agent")

SUFFIX = ".mcap"
METADATA = "metadata.yaml"  # what rosbag2 writes in the bag's folder when the bag is closed
MAGIC = b"\x89MCAP0\r\n"  # an MCAP file starts and ends with it
ROSBAG2 = "rosbag2"  # the depot's application for a rosbag2 bag's runs
MCAP = "mcap"  # ... and for a lone MCAP file's
DEFAULT_BAG_IDLE_S = 30.0
_METADATA_MAX_BYTES = 4 << 20  # a bag's metadata.yaml lists its topics and files: far less than this


@dataclass(frozen=True)
class Stamp:
    """What a file was when seen: another inode, size or mtime is another file to send."""

    inode: int
    size: int
    mtime_ns: int

    @classmethod
    def of(cls, st: os.stat_result) -> Stamp:
        return cls(st.st_ino, st.st_size, st.st_mtime_ns)


@dataclass(frozen=True)
class Bag:
    """A closed MCAP file to upload: where it goes at the depot, and the file as it was found."""

    path: str
    run_id: str
    application: str  # ROSBAG2 or MCAP
    stamp: Stamp
    is_mcap: bool  # starts with MCAP's magic (else the depot would refuse it: not sent)
    why: str  # what closed it ("metadata.yaml", "next split", "idle"), for the log


@dataclass
class Scan:
    """One pass over the watched folders."""

    closed: list[Bag] = field(default_factory=list)  # to upload, oldest first
    pending: list[str] = field(default_factory=list)  # found and not settled: still written, or to upload
    found: set[str] = field(default_factory=set)  # every MCAP file under the roots
    roots: tuple[str, ...] = ()  # the watched folders that exist


def is_bag_name(name: str) -> bool:
    """A file name the agent uploads: `*.mcap`, not hidden, not an editor's or copier's temp file
    (rsync's `.name.XXXX`, `name.mcap.part` and rosbag2's file-compressed `name.mcap.zstd` end
    otherwise or start with a dot)."""
    return name.endswith(SUFFIX) and not name.startswith((".", "~", "#")) and len(name) > len(SUFFIX)


def split_of(folder: str, name: str) -> int | None:
    """The split number of `name` if rosbag2 named it in `folder` (`FOLDER_N.mcap`), else None."""
    prefix = folder + "_"
    if not (name.startswith(prefix) and name.endswith(SUFFIX)):
        return None
    number = name[len(prefix) : -len(SUFFIX)]
    return int(number) if number.isascii() and number.isdigit() else None


def run_id_for(name: str) -> str:
    """A run id the depot takes (`core.ids.SAFE_ID`) made from a bag folder's or a file's name: each
    character it refuses becomes `_`; a name too long keeps its start and a digest of the whole,
    so two long names that share their start still name two runs."""
    cleaned = re.sub(r"[^A-Za-z0-9._-]", "_", name)
    if cleaned in ("", ".", ".."):
        cleaned = "bag" + cleaned
    if len(cleaned) > ID_LENGTH:
        digest = hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:12]
        cleaned = f"{cleaned[: ID_LENGTH - len(digest) - 1]}-{digest}"
    assert SAFE_ID.fullmatch(cleaned), cleaned
    return cleaned


def metadata_files(text: str) -> set[str] | None:
    """The file names a rosbag2 `metadata.yaml` lists (`relative_file_paths`, and the `files`
    entries' `path`), as base names: the oldest rosbag2 versions wrote them with the bag's folder
    in front. None if the text is not a bag's metadata (the file may be half written)."""
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError:
        return None
    info = data.get("rosbag2_bagfile_information") if isinstance(data, dict) else None
    if not isinstance(info, dict):
        return None
    names = info.get("relative_file_paths") or []
    files = info.get("files") or []
    if not isinstance(names, list) or not isinstance(files, list):
        return None
    listed = [str(n) for n in names] + [str(f["path"]) for f in files if isinstance(f, dict) and "path" in f]
    return {os.path.basename(n) for n in listed}


class BagScanner:
    """Finds the MCAP files under the watched folders and says which are closed. Remembers, per
    file, since when it has looked the same (on `clock`), which is what the idle rule needs: a
    restarted agent waits `idle_s` again before it calls a file closed by idleness alone."""

    def __init__(self, idle_s: float = DEFAULT_BAG_IDLE_S, *, clock: Callable[[], float] = time.monotonic) -> None:
        self.idle_s = idle_s
        self._clock = clock
        self._since: dict[str, tuple[Stamp, float]] = {}  # path -> its stamp, first seen at that stamp when
        self._metadata: dict[str, tuple[Stamp, set[str] | None]] = {}  # metadata.yaml path -> what it lists
        self._unreadable: set[str] = set()  # warned of once

    def scan(self, roots: Iterable[str | os.PathLike[str]], settled: Mapping[str, Stamp]) -> Scan:
        """The MCAP files under `roots` that are closed and not `settled` (uploaded, or refused, as
        they are now). Blocking: run it on a worker thread."""
        now = self._clock()
        result = Scan(roots=tuple(os.path.realpath(r) for r in roots if os.path.isdir(r)))
        folders: dict[str, list[str]] = {}
        for root in result.roots:
            for parent, dirs, files in os.walk(root):
                dirs[:] = [d for d in dirs if not d.startswith(".")]  # hidden folders are skipped
                names = sorted(n for n in files if is_bag_name(n))
                if names:
                    folders[parent] = names
        seen: dict[str, tuple[Stamp, float]] = {}
        for folder, names in folders.items():
            for bag in self._folder(folder, names, settled, now, seen, result):
                result.closed.append(bag)
        self._since = seen  # files gone are forgotten
        self._unreadable &= result.found
        self._metadata = {p: m for p, m in self._metadata.items() if os.path.dirname(p) in folders}
        result.closed.sort(key=lambda b: (b.stamp.mtime_ns, b.path))
        return result

    def _folder(
        self,
        folder: str,
        names: list[str],
        settled: Mapping[str, Stamp],
        now: float,
        seen: dict[str, tuple[Stamp, float]],
        result: Scan,
    ) -> Iterable[Bag]:
        base = os.path.basename(folder)
        listed = self._listed(os.path.join(folder, METADATA))
        splits = {name: split_of(base, name) for name in names}
        rosbag = listed is not None or any(n is not None for n in splits.values())
        last_split = max((n for n in splits.values() if n is not None), default=None)
        for name in names:
            path = os.path.join(folder, name)
            try:
                stamp = Stamp.of(os.stat(path))
            except FileNotFoundError:
                continue
            result.found.add(path)
            if settled.get(path) == stamp:
                continue
            result.pending.append(path)
            before = self._since.get(path)
            since = before[1] if before is not None and before[0] == stamp else now
            seen[path] = (stamp, since)
            split = splits[name]
            if listed is not None and name in listed:
                writer_says = "metadata.yaml"
            elif split is not None and last_split is not None and split < last_split:
                writer_says = "next split"
            else:
                writer_says = ""
            ends = _ends(path, stamp.size)
            if ends is None:  # unreadable (its permissions): looked at again at every scan
                if path not in self._unreadable:
                    log.warning("%s cannot be read: not uploaded until it can", path)
                self._unreadable.add(path)
                continue
            self._unreadable.discard(path)
            head, tail = ends
            if writer_says and tail == MAGIC:
                why = writer_says
            elif now - since >= self.idle_s:
                why = "idle"
            else:
                continue
            run = run_id_for(base) if rosbag else run_id_for(name[: -len(SUFFIX)])
            yield Bag(path, run, ROSBAG2 if rosbag else MCAP, stamp, head == MAGIC, why)

    def _listed(self, path: str) -> set[str] | None:
        """What the folder's metadata.yaml lists (None: there is none, or it is not a bag's),
        read again only when it changed."""
        try:
            stamp = Stamp.of(os.stat(path))
        except OSError:
            self._metadata.pop(path, None)
            return None
        cached = self._metadata.get(path)
        if cached is not None and cached[0] == stamp:
            return cached[1]
        listed: set[str] | None = None
        if stamp.size <= _METADATA_MAX_BYTES:
            try:
                listed = metadata_files(Path(path).read_text(encoding="utf-8", errors="replace"))
            except OSError as exc:
                log.debug("cannot read %s (%s): its bag's files close by idleness", path, exc)
        self._metadata[path] = (stamp, listed)
        return listed


def _ends(path: str, size: int) -> tuple[bytes, bytes] | None:
    """The file's first and last 8 bytes (of its first `size`; empty for a file too small to be an
    MCAP file's); None if it cannot be read."""
    try:
        with open(path, "rb") as fh:
            if size < 2 * len(MAGIC):
                return b"", b""
            head = fh.read(len(MAGIC))
            fh.seek(size - len(MAGIC))
            return head, fh.read(len(MAGIC))
    except OSError:
        return None
