"""MCAP to RRD with Rerun's own loader: `rerun mcap convert` from the pinned rerun-sdk wheel (or the
CLI `FLEET_RERUN_CLI` names, after an upgrade), in a child process with limits on its time, its
memory and the size of what it writes, so a hostile bag costs the depot at most those.

The output limit is set inside the child (RLIMIT_FSIZE), by a small Python launcher that calls
`setrlimit` and then `exec`s the CLI: `preexec_fn` is unsafe in a process that runs threads, as the
depot does. Memory is watched from outside (the child's anonymous resident memory, read from /proc
every WATCH_S): the CLI maps the whole MCAP file into its address space, so an address-space limit
would refuse big bags rather than hungry ones, and with one the CLI logs an error and exits 0.

The CLI also exits 0 when it logged an error and converted nothing (a file it cannot map, say): an
ERROR line, or nothing processed of a file that holds messages, is a failure.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from core.errors import ConversionLimitError, InvalidMcapError, UnavailableError

log = logging.getLogger(__name__)

STDERR_TAIL = 4000  # bytes of the CLI's own words kept for the reason of a failure
WATCH_S = 0.1
PROCESSED = re.compile(r"Processed (\d+) messages")
LAUNCHER = """
import os, resource, sys
output = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (output, output))
resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
os.execv(sys.argv[2], sys.argv[2:])
"""


@dataclass(frozen=True)
class Limits:
    timeout_s: float
    memory_bytes: int
    output_bytes: int


@functools.cache
def cli_path(configured: str | None) -> str:
    """The `rerun` executable: the configured one, else the binary of the installed rerun-sdk (its
    `rerun_cli` package), else `rerun` on PATH; UnavailableError if there is none."""
    if configured:
        found = shutil.which(configured)
        if found is None:
            raise UnavailableError(f"FLEET_RERUN_CLI is {configured!r}, which is not an executable")
        return found
    spec = importlib.util.find_spec("rerun_cli")
    if spec is not None and spec.origin is not None:
        binary = Path(spec.origin).parent / "rerun"
        if binary.is_file() and os.access(binary, os.X_OK):
            return str(binary)
    found = shutil.which("rerun")
    if found is None:
        raise UnavailableError(
            "this depot cannot convert MCAP: the Rerun CLI is not installed (pip install rerun-sdk, "
            "or set FLEET_RERUN_CLI to its `rerun`)"
        )
    return found


@functools.cache
def cli_version(cli: str) -> str:
    """`rerun-cli 0.41.0` of the CLI's `--version`, as the converter an import records."""
    try:
        out = subprocess.run([cli, "--version"], capture_output=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise UnavailableError(f"the Rerun CLI {cli} does not answer `--version` ({exc})") from None
    words = out.decode(errors="replace").split()
    return " ".join(words[:2])[:64]


def convert(
    cli: str, source: Path, target: Path, *, recording_id: str, application_id: str, limits: Limits, messages: int
) -> None:
    """Convert the `messages` messages of `source` into `target`; InvalidMcapError with the CLI's
    reason if it cannot, ConversionLimitError if it went past a limit (target removed either way)."""
    command = [
        sys.executable,
        "-c",
        LAUNCHER,
        str(limits.output_bytes),
        cli,
        "mcap",
        "convert",
        str(source),
        "-o",
        str(target),
        "--recording-id",
        recording_id,
        "--application-id",
        application_id,
    ]
    env = {**os.environ, "RUST_LOG": "info", "RUST_BACKTRACE": "0"}
    stderr = target.with_name(target.name + ".stderr")
    with open(stderr, "wb") as err:
        process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err, env=env, start_new_session=True
        )
        try:
            code = _watch(process, limits)
        except ConversionLimitError:
            target.unlink(missing_ok=True)
            stderr.unlink(missing_ok=True)
            raise
    said = _tail(stderr)
    stderr.unlink(missing_ok=True)
    plain = _plain(said)
    processed = [int(n) for n in PROCESSED.findall(plain)]
    errors = [line.strip() for line in plain.splitlines() if " ERROR " in line]
    nothing = messages > 0 and (not processed or processed[-1] == 0)
    if code == 0 and target.exists() and not errors and not nothing:
        return
    target.unlink(missing_ok=True)
    if code == 0:
        why = errors[-1][:500] if errors else "it converted nothing"
        raise InvalidMcapError(f"the Rerun CLI could not convert the file's {messages} messages: {why}")
    raise _failure(code, said, limits)


def _watch(process: subprocess.Popen[bytes], limits: Limits) -> int:
    """Wait for the child within its time and memory; its exit code. Past either, it is killed."""
    deadline = time.monotonic() + limits.timeout_s
    while True:
        try:
            return process.wait(timeout=max(0.0, min(WATCH_S, deadline - time.monotonic())))
        except subprocess.TimeoutExpired:
            pass
        if time.monotonic() >= deadline:
            _kill(process)
            raise ConversionLimitError(f"the conversion took longer than {limits.timeout_s:g} s (FLEET_MCAP_TIMEOUT_S)")
        used = anonymous_rss(process.pid)
        if used > limits.memory_bytes:
            _kill(process)
            raise ConversionLimitError(
                f"the conversion needed more than {limits.memory_bytes >> 20:,} MiB of memory (FLEET_MCAP_MEMORY_MB)"
            )


def anonymous_rss(pid: int) -> int:
    """A process's resident anonymous memory in bytes (its mapped file pages left out); 0 if gone."""
    try:
        with open(f"/proc/{pid}/status", "rb") as f:
            for line in f:
                if line.startswith(b"RssAnon:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return 0


def _failure(code: int, said: str, limits: Limits) -> Exception:
    if code == -signal.SIGXFSZ:
        return ConversionLimitError(
            f"the converted recording would be larger than {limits.output_bytes:,} bytes (FLEET_MCAP_MAX_OUTPUT_RATIO)"
        )
    if "memory allocation" in said or "out of memory" in said.lower():
        return ConversionLimitError(f"the conversion ran out of memory: {_last_line(said)}")
    return InvalidMcapError(
        f"the Rerun CLI could not convert the file (exit {code}): {_last_line(said) or 'no reason given'}"
    )


def _kill(process: subprocess.Popen[bytes]) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    process.wait()


def _tail(path: Path) -> str:
    try:
        with open(path, "rb") as f:
            f.seek(max(0, path.stat().st_size - STDERR_TAIL))
            return f.read().decode(errors="replace")
    except OSError:
        return ""


def _last_line(said: str) -> str:
    """The CLI's last words (its error), without terminal colours, at most 500 characters."""
    lines = [line.strip() for line in _plain(said).splitlines() if line.strip()]
    errors = [line for line in lines if "error" in line.lower()]
    return (errors[-1] if errors else lines[-1] if lines else "")[:500]


def _plain(text: str) -> str:
    out, skipping = [], False
    for ch in text:
        if ch == "\x1b":
            skipping = True
        elif skipping and ch.isalpha():
            skipping = False
        elif not skipping:
            out.append(ch)
    return "".join(out)
