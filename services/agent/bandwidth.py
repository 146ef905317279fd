"""Sharing the agent's one uplink between live data, backfill and pulls, under a bandwidth cap.

The model is one token bucket per connection. Tokens are bytes. They flow in at the cap in force,
which a `RateSchedule` gives (rules by time of day and by which network interface is up, first
match wins, else a default). The bucket holds at most `burst_s` seconds of tokens, so an idle link
cannot save up more than a short burst. Before sending a message, a sender asks for its size
(`TokenBucket.acquire`) and goes when the bucket holds that much. A message bigger than the whole
bucket goes when the bucket is full and leaves it in debt; later senders wait the debt out, so the
average still holds.

Senders queue by priority: live data first, then the windows of high-priority triggers, then
backfill, then pulls (and normal triggers' windows); first come, first served within a class.
Only the sender at the head of the queue sleeps on a timer, never more than a second at a time, so
a cap that changes while it waits (the dock's network comes up, a time window opens) takes effect
within about a second.
"""

from __future__ import annotations

import asyncio
import collections
import dataclasses
import datetime as dt
import enum
import math
import re
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from pathlib import Path
from typing import Protocol

DEFAULT_SYSFS_NET = Path("/sys/class/net")
INTERFACE_CACHE_S = 1.0  # how long an interface's state read from sysfs is trusted
RATE_RECHECK_S = 1.0  # the longest a waiting sender sleeps before it reads the cap again
DEFAULT_BURST_S = 0.25
# Float rounding can leave a waiter a hair short of its tokens after sleeping exactly as long as
# it was told; without this slack it would sleep again for a few nanoseconds.
_SLACK_BYTES = 1.0


class Priority(enum.IntEnum):
    """The kinds of traffic on the uplink; a lower number is served first."""

    LIVE = 0
    TRIGGER = 1  # the window of a `priority = "high"` trigger: after live data, before backfill
    BACKFILL = 2
    PULL = 3  # a person's pull, and a normal trigger's window


# --- rates as people type them ---------------------------------------------------------------

_RATE = re.compile(r"(?P<number>\d+(?:\.\d*)?|\.\d+)\s*(?P<unit>[a-z]*)(?:/s)?")
_RATE_UNITS = {
    "": 1,
    "b": 1,
    "k": 1000,
    "kb": 1000,
    "m": 1000**2,
    "mb": 1000**2,
    "g": 1000**3,
    "gb": 1000**3,
    "kib": 1024,
    "mib": 1024**2,
    "gib": 1024**3,
}
_RATE_HELP = (
    "bytes per second as a number with an optional unit, like 200000, 500k, 2M, 1.5MB or 512KiB "
    "(k, M, G: powers of 1000; KiB, MiB, GiB: powers of 1024; 0 for unlimited)"
)


def parse_rate(text: str) -> int:
    """Bytes per second from text like "500k", "2M", "1.5MB", "512KiB" or "200000"; 0 is unlimited."""
    match = _RATE.fullmatch(text.strip().lower())
    if match is None or match["unit"] not in _RATE_UNITS:
        raise ValueError(f"{text!r} is not a rate: {_RATE_HELP}")
    exact = float(match["number"]) * _RATE_UNITS[match["unit"]]
    if not math.isfinite(exact):
        raise ValueError(f"{text!r} is too large a rate: {_RATE_HELP}")
    rate = round(exact)
    if rate == 0 and exact > 0:  # would read as unlimited, the opposite of what was meant
        raise ValueError(f"{text!r} is less than one byte per second: give at least 1, or 0 for unlimited")
    return rate


# --- the schedule ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class RateRule:
    """One rule of a schedule: its cap holds while the time of day is in [start, end) and its
    interface is up; a rule without a window holds all day, one without an interface anywhere."""

    bytes_per_s: int  # 0: unlimited
    start: dt.time | None = None
    end: dt.time | None = None  # before start: the window wraps midnight
    interface: str | None = None

    def in_window(self, moment: dt.time) -> bool:
        if self.start is None or self.end is None:
            return True
        if self.start < self.end:
            return self.start <= moment < self.end
        return moment >= self.start or moment < self.end


_RULE_FIELDS = ("from", "to", "interface", "bytes_per_s")
_TIME_OF_DAY = re.compile(r"(\d{1,2}):(\d{2})")
# Linux interface names: at most 15 bytes, never "/" or whitespace (the name is a sysfs folder).
_INTERFACE = re.compile(r"[^/\s\x00]{1,15}")


def parse_rules(raw: Sequence[Mapping[str, object]]) -> list[RateRule]:
    """Rules from the config file's `[[agent_bandwidth_rules]]` tables (keys `from`, `to` as "HH:MM"
    local time, `interface`, `bytes_per_s`), in order. A bad rule is one `ValueError` naming the rule
    (counting from 1, as they appear in the file) and the field."""
    return [_parse_rule(number, entry) for number, entry in enumerate(raw, start=1)]


def _rule_error(number: int, field: str, problem: str) -> ValueError:
    return ValueError(f"bandwidth rule {number}, field {field!r}: {problem}")


def _parse_rule(number: int, entry: object) -> RateRule:
    if not isinstance(entry, Mapping):
        raise ValueError(
            f"bandwidth rule {number}: is a {type(entry).__name__}, not a table with keys {', '.join(_RULE_FIELDS)}"
        )
    unknown = sorted(str(key) for key in entry if key not in _RULE_FIELDS)
    if unknown:
        raise _rule_error(number, unknown[0], f"is not a rule field: use {', '.join(_RULE_FIELDS)}")
    if "bytes_per_s" not in entry:
        raise _rule_error(number, "bytes_per_s", "is missing: give the cap in bytes per second (0 for unlimited)")
    start = _rule_time(number, "from", entry.get("from"))
    end = _rule_time(number, "to", entry.get("to"))
    if (start is None) != (end is None):
        missing = "to" if end is None else "from"
        raise _rule_error(number, missing, "is missing: a time window needs both 'from' and 'to' (HH:MM)")
    if start is not None and start == end:
        raise _rule_error(number, "to", "is the same time as 'from': leave both out for a rule that holds all day")
    return RateRule(
        bytes_per_s=_rule_rate(number, entry["bytes_per_s"]),
        start=start,
        end=end,
        interface=_rule_interface(number, entry.get("interface")),
    )


def _rule_time(number: int, field: str, value: object) -> dt.time | None:
    if value is None:
        return None
    if isinstance(value, dt.time):  # TOML's unquoted local time, like 22:00:00
        return value.replace(tzinfo=None)
    match = _TIME_OF_DAY.fullmatch(value.strip()) if isinstance(value, str) else None
    if match is None or int(match[1]) > 23 or int(match[2]) > 59:
        raise _rule_error(number, field, f'{value!r} is not a time of day: give local time as HH:MM, like "22:30"')
    return dt.time(int(match[1]), int(match[2]))


def _rule_rate(number: int, value: object) -> int:
    if isinstance(value, str):
        try:
            return parse_rate(value)
        except ValueError as err:
            raise _rule_error(number, "bytes_per_s", str(err)) from None
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise _rule_error(
            number,
            "bytes_per_s",
            f'{value!r} is not a rate: give whole bytes per second (0 for unlimited) or text like "500k"',
        )
    return value


def _rule_interface(number: int, value: object) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or not _INTERFACE.fullmatch(value) or value in (".", ".."):
        raise _rule_error(
            number, "interface", f'{value!r} is not a network interface name: give one like "eth0" or "wlan0"'
        )
    return value


class RateSchedule:
    """The cap at a given moment: the first rule that holds, else the default. None is unlimited."""

    def __init__(
        self,
        rules: Sequence[RateRule] = (),
        default: int | None = None,
        *,
        sysfs_root: str | Path = DEFAULT_SYSFS_NET,
        now: Callable[[], dt.datetime] = dt.datetime.now,
        monotonic: Callable[[], float] = time.monotonic,
        cache_s: float = INTERFACE_CACHE_S,
    ) -> None:
        if default is not None and default < 0:
            raise ValueError(f"the default bandwidth {default} is negative: give bytes per second, or 0 for unlimited")
        self.rules = tuple(rules)
        self.default = default or None
        self._sysfs_root = Path(sysfs_root)
        self._now = now  # local time of day, as the rules' windows are written
        self._monotonic = monotonic
        self._cache_s = cache_s
        self._interfaces: dict[str, tuple[float, bool]] = {}  # name -> (read at, up)

    @classmethod
    def from_config(
        cls,
        rules: Sequence[Mapping[str, object]],
        default: int | str | None = None,
        *,
        sysfs_root: str | Path = DEFAULT_SYSFS_NET,
    ) -> RateSchedule:
        """A schedule from the config file's rules and a default cap (bytes per second or text like "200k")."""
        if isinstance(default, str):
            default = parse_rate(default)
        return cls(parse_rules(rules), default, sysfs_root=sysfs_root)

    def current(self) -> int | None:
        """The cap now, in bytes per second; None is unlimited."""
        return self.rate_at(self._now().time())

    def rate_at(self, moment: dt.time) -> int | None:
        """The cap at this local time of day, with the interfaces as they are now; None is unlimited."""
        for rule in self.rules:
            if rule.in_window(moment) and (rule.interface is None or self.interface_up(rule.interface)):
                return rule.bytes_per_s or None
        return self.default

    def interface_up(self, name: str) -> bool:
        """Whether the interface is up, as sysfs said within the last `cache_s` seconds."""
        now = self._monotonic()
        cached = self._interfaces.get(name)
        if cached is not None and now - cached[0] < self._cache_s:
            return cached[1]
        up = self._read_interface(name)
        self._interfaces[name] = (now, up)
        return up

    def _read_interface(self, name: str) -> bool:
        folder = self._sysfs_root / name
        state = _read_sysfs(folder / "operstate")
        if state == "up":
            return True
        # Loopback and some tunnels never report up, only unknown; their carrier says whether they carry.
        return state == "unknown" and _read_sysfs(folder / "carrier") == "1"


def _read_sysfs(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:  # no such interface, or the carrier of one that is down (EINVAL)
        return None


# --- the bucket ------------------------------------------------------------------------------


class RateSource(Protocol):
    """Where a bucket reads its cap: a `RateSchedule`, or anything that says the cap now."""

    def current(self) -> int | None: ...


@dataclasses.dataclass(eq=False)
class _Waiter:
    nbytes: int
    wake: asyncio.Event = dataclasses.field(default_factory=asyncio.Event)


class TokenBucket:
    """Paces sends to the cap a `RateSource` gives, serving waiting senders in priority order."""

    def __init__(
        self,
        rate: RateSource | int | None,
        *,
        burst_s: float = DEFAULT_BURST_S,
        clock: Callable[[], float] | None = None,
        sleep: Callable[[float], Awaitable[None]] | None = None,
    ) -> None:
        """`rate`: a schedule, or a fixed cap in bytes per second (0 or None: unlimited). `clock`
        (monotonic seconds) and `sleep` default to the running loop's time and `asyncio.sleep`."""
        if not burst_s > 0:
            raise ValueError(f"burst_s {burst_s} must be more than 0 seconds, like {DEFAULT_BURST_S}")
        self._source: RateSource = RateSchedule(default=rate) if rate is None or isinstance(rate, int) else rate
        self._burst_s = burst_s
        self._clock = clock
        self._sleep = sleep if sleep is not None else asyncio.sleep
        self._queues: dict[Priority, collections.deque[_Waiter]] = {p: collections.deque() for p in Priority}
        self._sent = dict.fromkeys(Priority, 0)
        self._waiting = dict.fromkeys(Priority, 0)
        self._tokens = math.inf  # clamped to a full bucket at the first read of the cap
        self._rate: int | None = None  # the cap read last, in force since `_checked_at`
        self._checked_at: float | None = None
        self._timed: _Waiter | None = None  # the one waiter sleeping on a timer, if any

    @property
    def sent_bytes(self) -> dict[Priority, int]:
        """Bytes let through so far, by priority."""
        return dict(self._sent)

    @property
    def waiting(self) -> dict[Priority, int]:
        """Bytes queued now, by priority."""
        return dict(self._waiting)

    async def acquire(self, nbytes: int, priority: Priority) -> None:
        """Waits until `nbytes` may be sent under the cap, behind waiters of a lower priority
        number and those of the same priority that came first."""
        if nbytes < 0:
            raise ValueError(f"cannot send {nbytes} bytes: give the message's size, 0 or more")
        priority = Priority(priority)
        if nbytes > 0 and (self._queued_ahead(priority) or self._take(nbytes) > 0):
            await self._wait_in_line(nbytes, priority)
        self._sent[priority] += nbytes

    def _queued_ahead(self, priority: Priority) -> bool:
        return any(self._queues[p] for p in Priority if p <= priority)

    def _head(self) -> _Waiter | None:
        for queue in self._queues.values():  # in priority order
            if queue:
                return queue[0]
        return None

    async def _wait_in_line(self, nbytes: int, priority: Priority) -> None:
        waiter = _Waiter(nbytes)
        self._queues[priority].append(waiter)
        self._waiting[priority] += nbytes
        self._nudge()
        try:
            while True:
                waiter.wake.clear()  # before looking, so a change after the look wakes it
                if self._head() is not waiter:
                    await waiter.wake.wait()
                    continue
                delay = self._take(nbytes)
                if delay == 0:
                    return
                await self._sleep_unless_woken(waiter, min(delay, RATE_RECHECK_S))
        finally:  # taken, or cancelled: either way out of the line, and the next head told
            self._queues[priority].remove(waiter)
            self._waiting[priority] -= nbytes
            self._nudge()

    def _nudge(self) -> None:
        """After the line changed: wake a new head so it looks at the bucket, and a sleeper that is
        no longer the head so it gives up its timer."""
        head = self._head()
        if head is not None and head is not self._timed:
            head.wake.set()
        if self._timed is not None and self._timed is not head:
            self._timed.wake.set()

    async def _sleep_unless_woken(self, waiter: _Waiter, delay: float) -> None:
        self._timed = waiter
        sleeping = asyncio.ensure_future(self._sleep(delay))
        woken = asyncio.ensure_future(waiter.wake.wait())
        try:
            await asyncio.wait((sleeping, woken), return_when=asyncio.FIRST_COMPLETED)
        finally:
            self._timed = None
            sleeping.cancel()
            woken.cancel()
        if sleeping.done() and not sleeping.cancelled():
            sleeping.result()  # a failing sleep is the caller's to see, not a reason to spin

    def _take(self, nbytes: int) -> float:
        """Takes `nbytes` from the bucket if they may go now and returns 0; else returns how many
        seconds until they may, at the current cap."""
        rate = self._refill()
        if rate is None:
            return 0.0
        need = min(nbytes, self._capacity(rate))  # a message bigger than the bucket waits for a full one
        if self._tokens + _SLACK_BYTES >= need:
            self._tokens -= nbytes  # below zero for such a message: later senders wait out the debt
            return 0.0
        return (need - self._tokens) / rate

    def _refill(self) -> int | None:
        """Adds the tokens earned since the last look, at the cap that was in force, and reads the cap."""
        now = self._clock() if self._clock is not None else asyncio.get_running_loop().time()
        if self._checked_at is not None and self._rate is not None:
            self._tokens += max(0.0, now - self._checked_at) * self._rate
        self._checked_at = now
        self._rate = self._source.current() or None
        if self._rate is None:
            self._tokens = math.inf
        else:
            self._tokens = min(self._tokens, self._capacity(self._rate))
        return self._rate

    def _capacity(self, rate: int) -> float:
        return max(rate * self._burst_s, 1.0)
