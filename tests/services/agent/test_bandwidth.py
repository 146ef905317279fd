"""The uplink's bandwidth cap: the token bucket holds the rate (measured in real time, and exactly
in virtual time), serves live data before backfill before pulls, lets oversized messages through
without breaking the average, and follows a schedule whose cap changes while senders wait."""

from __future__ import annotations

import asyncio
import datetime as dt
import selectors
import time
import tomllib
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from services.agent.bandwidth import (
    RATE_RECHECK_S,
    Priority,
    RateRule,
    RateSchedule,
    TokenBucket,
    parse_rate,
    parse_rules,
)

pytestmark = pytest.mark.timeout(30)  # a sender that never gets its turn fails here, not after 10 minutes

# --- virtual time: the loop's clock jumps to the next timer instead of waiting for it --------


class _VirtualSelector(selectors.DefaultSelector):  # type: ignore[misc, valid-type]
    def __init__(self) -> None:
        super().__init__()
        self.now = 1000.0

    def select(self, timeout: float | None = None) -> list[Any]:
        if timeout is None:  # nothing scheduled: only a thread can wake the loop (its shutdown)
            return super().select(None)  # type: ignore[no-any-return]
        events = super().select(0)
        if not events:
            self.now += timeout
        return events  # type: ignore[no-any-return]


class VirtualTimeLoop(asyncio.SelectorEventLoop):
    def __init__(self) -> None:
        self._virtual = _VirtualSelector()
        super().__init__(self._virtual)

    def time(self) -> float:
        return float(self._virtual.now)


def run_virtual(main: Callable[[], Awaitable[Any]]) -> Any:
    with asyncio.Runner(loop_factory=VirtualTimeLoop) as runner:
        return runner.run(main())  # type: ignore[arg-type]


def now() -> float:
    return asyncio.get_running_loop().time()


async def until(condition: Callable[[], bool]) -> None:
    """Lets the other tasks run until the condition holds (in virtual time, without moving the clock)."""
    for _ in range(1000):
        if condition():
            return
        await asyncio.sleep(0)
    raise AssertionError("the condition never held")


class SteppedRate:
    """A cap that changes at given loop times: [(from_time, bytes_per_s), ...]."""

    def __init__(self, steps: list[tuple[float, int | None]]) -> None:
        self.steps = steps

    def current(self) -> int | None:
        rate = None
        for start, value in self.steps:
            if now() >= start:
                rate = value
        return rate


# --- (a) the measured rate -------------------------------------------------------------------


@pytest.mark.slow
def test_the_measured_rate_holds_the_cap_in_real_time():
    cap, message = 1_000_000, 32 * 1024
    senders = len(Priority)
    per_sender = 3_000_000 // senders  # 3 MB in about 3 s, one sender per priority

    async def main() -> float:
        bucket = TokenBucket(cap)
        await bucket.acquire(int(cap * 0.25), Priority.LIVE)  # the bucket starts full: spend that first
        began = time.monotonic()

        async def sender(priority: Priority) -> None:
            left = per_sender
            while left > 0:
                await bucket.acquire(min(message, left), priority)
                left -= message

        await asyncio.gather(*(sender(p) for p in Priority))
        assert sum(bucket.sent_bytes.values()) == senders * per_sender + int(cap * 0.25)
        return senders * per_sender / (time.monotonic() - began)

    achieved = asyncio.run(main())
    assert abs(achieved - cap) / cap < 0.10, f"{achieved:.0f} B/s against a cap of {cap}"


def test_the_rate_is_exact_in_virtual_time():
    async def main() -> None:
        bucket = TokenBucket(1000)  # a 250-byte bucket, full at the start
        began = now()
        done_at = []
        for _ in range(100):
            await bucket.acquire(100, Priority.LIVE)
            done_at.append(now() - began)
        assert done_at[-1] == pytest.approx((100 * 100 - 250) / 1000, abs=1e-3)
        # Over any two seconds, no more than two seconds' worth plus one bucket went.
        for i, start in enumerate(done_at):
            sent = sum(100 for t in done_at[i:] if t < start + 2.0)
            assert sent <= 2 * 1000 + 250
        assert bucket.sent_bytes == {Priority.LIVE: 10_000, Priority.TRIGGER: 0, Priority.BACKFILL: 0, Priority.PULL: 0}

    run_virtual(main)


def test_a_waiter_sleeps_at_most_a_second_at_a_time_and_never_spins():
    slept: list[float] = []

    async def main() -> None:
        async def sleep(seconds: float) -> None:
            slept.append(seconds)
            await asyncio.sleep(seconds)

        bucket = TokenBucket(1000, clock=now, sleep=sleep)
        began = now()
        await bucket.acquire(250, Priority.LIVE)  # the full bucket
        await bucket.acquire(4500, Priority.BACKFILL)  # waits for a full bucket: 0.25 s
        await bucket.acquire(200, Priority.PULL)  # then the debt of 4250 and its own 200: 4.45 s
        assert now() - began == pytest.approx(4.7, abs=1e-3)

    run_virtual(main)
    assert max(slept) <= RATE_RECHECK_S
    assert len(slept) <= 7, slept  # 0.25, then five of at most a second


def test_unlimited_returns_at_once():
    async def main() -> None:
        for rate in (None, 0):
            bucket = TokenBucket(rate, sleep=_no_sleep)
            began = now()
            for _ in range(3):
                await bucket.acquire(10**9, Priority.PULL)
            assert now() == began
            assert bucket.sent_bytes[Priority.PULL] == 3 * 10**9

    run_virtual(main)


async def _no_sleep(seconds: float) -> None:
    raise AssertionError(f"slept {seconds} s under no cap")


def test_bad_requests_are_refused():
    with pytest.raises(ValueError, match="-1 bytes"):
        asyncio.run(TokenBucket(1000).acquire(-1, Priority.LIVE))
    with pytest.raises(ValueError, match="burst_s"):
        TokenBucket(1000, burst_s=0)
    with pytest.raises(ValueError, match="negative"):
        TokenBucket(-5)


# --- (b) priority ----------------------------------------------------------------------------


def test_live_goes_first_then_trigger_windows_then_backfill_and_pulls_last():
    async def main() -> None:
        bucket = TokenBucket(1000)
        order: list[str] = []
        finished: dict[str, float] = {}

        async def send(name: str, nbytes: int, priority: Priority) -> None:
            await bucket.acquire(nbytes, priority)
            order.append(name)
            finished[name] = now()

        tasks = [asyncio.create_task(send("P1", 500, Priority.PULL))]
        tasks += [asyncio.create_task(send(f"B{i}", 500, Priority.BACKFILL)) for i in range(1, 5)]
        await until(lambda: bucket.waiting[Priority.BACKFILL] == 2000)
        began = now()
        # P1 took the full bucket (it was alone) and left it 250 in debt; the rest queue behind it.
        assert order == ["P1"]
        assert bucket.waiting == {Priority.LIVE: 0, Priority.TRIGGER: 0, Priority.BACKFILL: 2000, Priority.PULL: 0}
        tasks.append(asyncio.create_task(send("P2", 100, Priority.PULL)))
        await asyncio.sleep(0.1)
        tasks.append(asyncio.create_task(send("T1", 100, Priority.TRIGGER)))  # a high-priority trigger's window
        tasks.append(asyncio.create_task(send("L1", 500, Priority.LIVE)))
        await asyncio.gather(*tasks)

        assert order == ["P1", "L1", "T1", "B1", "B2", "B3", "B4", "P2"]
        # L1 waited only for the debt and a bucket's worth, as if no backfill were queued.
        assert finished["L1"] - began == pytest.approx(0.5, abs=1e-3)
        assert bucket.waiting == dict.fromkeys(Priority, 0)
        assert bucket.sent_bytes == {
            Priority.LIVE: 500,
            Priority.TRIGGER: 100,
            Priority.BACKFILL: 2000,
            Priority.PULL: 600,
        }

    run_virtual(main)


def test_live_goes_at_once_past_queued_backfill_when_the_bucket_holds_enough():
    async def main() -> None:
        bucket = TokenBucket(1000, burst_s=1.0)  # a 1000-byte bucket
        backfill = asyncio.create_task(bucket.acquire(5000, Priority.BACKFILL))  # waits for a full bucket
        await bucket.acquire(600, Priority.LIVE)  # the bucket starts full
        await until(lambda: bucket.waiting[Priority.BACKFILL] == 5000)
        began = now()
        await asyncio.sleep(0.3)
        await bucket.acquire(300, Priority.LIVE)  # 400 left + 300 earned: no wait
        assert now() - began == pytest.approx(0.3, abs=1e-6)
        assert not backfill.done()
        await backfill
        assert now() - began == pytest.approx(0.9, abs=1e-3)  # from 400 back to a full 1000 at 1000 B/s

    run_virtual(main)


def test_a_cancelled_waiter_leaves_the_line():
    async def main() -> None:
        bucket = TokenBucket(1000)
        await bucket.acquire(250, Priority.LIVE)
        first = asyncio.create_task(bucket.acquire(1000, Priority.BACKFILL))
        second = asyncio.create_task(bucket.acquire(100, Priority.BACKFILL))
        await until(lambda: bucket.waiting[Priority.BACKFILL] == 1100)
        began = now()
        first.cancel()
        with pytest.raises(asyncio.CancelledError):
            await first
        await second
        assert now() - began == pytest.approx(0.1, abs=1e-3)
        assert bucket.waiting == dict.fromkeys(Priority, 0)
        assert bucket.sent_bytes[Priority.BACKFILL] == 100

    run_virtual(main)


# --- (c) messages bigger than the bucket -----------------------------------------------------


def test_a_message_bigger_than_the_bucket_passes_and_the_average_holds():
    async def main() -> None:
        bucket = TokenBucket(1000)  # a 250-byte bucket
        began = now()
        await bucket.acquire(5000, Priority.PULL)  # twenty buckets at once: goes, leaving a debt
        assert now() == began
        await bucket.acquire(100, Priority.LIVE)  # waits out the debt
        assert now() - began == pytest.approx((5000 - 250 + 100) / 1000, abs=1e-3)
        for _ in range(9):
            await bucket.acquire(5000, Priority.PULL)
        # The average holds once the last debt is paid: the next sender goes as if all had been paced.
        await bucket.acquire(1, Priority.LIVE)
        elapsed = now() - began
        assert elapsed == pytest.approx((10 * 5000 + 100 + 1 - 250) / 1000, abs=1e-3)
        assert (10 * 5000 + 100 + 1) / elapsed <= 1000 * 1.01

    run_virtual(main)


# --- (e) the cap changing while senders wait -------------------------------------------------


def test_a_faster_cap_mid_wait_is_honoured_within_a_second():
    async def main() -> None:
        began = now()
        bucket = TokenBucket(SteppedRate([(0, 1000), (began + 2.0, 100_000)]))
        await bucket.acquire(10_000, Priority.PULL)  # goes (the bucket is full), leaving 9750 in debt
        await bucket.acquire(100, Priority.BACKFILL)  # about 10 s at 1000 B/s
        assert 2.0 <= now() - began <= 2.0 + RATE_RECHECK_S

    run_virtual(main)


def test_a_slower_cap_mid_stream_is_honoured():
    async def main() -> None:
        began = now()
        bucket = TokenBucket(SteppedRate([(0, 10_000), (began + 0.5, 1000)]))
        sent_at: list[float] = []
        while now() - began < 6.0:
            await bucket.acquire(1000, Priority.LIVE)
            sent_at.append(now() - began)
        after_the_change = 1000 * sum(1 for t in sent_at if t >= 1.5)
        assert 3000 <= after_the_change <= 6000, sent_at  # 4.5 s at 1 kB/s, not at 10 kB/s

    run_virtual(main)


def test_the_dock_coming_up_lifts_the_cap_of_a_waiting_sender(tmp_path: Path):
    sysfs = fake_sysfs(tmp_path, eth0="down")

    async def main() -> None:
        schedule = RateSchedule(
            parse_rules([{"interface": "eth0", "bytes_per_s": 0}]), 1000, sysfs_root=sysfs, monotonic=now
        )
        bucket = TokenBucket(schedule)
        began = now()
        await bucket.acquire(50_000, Priority.PULL)  # goes (the bucket is full), leaving a debt of 50 s
        sender = asyncio.create_task(bucket.acquire(100, Priority.PULL))
        await asyncio.sleep(3.0)
        assert not sender.done()
        (sysfs / "eth0" / "operstate").write_text("up\n")
        await sender
        # Seen at the next look after the cached state expires: within a second, plus a second.
        assert 3.0 <= now() - began <= 3.0 + 1.0 + RATE_RECHECK_S

    run_virtual(main)


def test_a_time_window_opening_mid_wait_lifts_the_cap():
    async def main() -> None:
        two_to_eight = dt.datetime(2026, 5, 4, 7, 59, 58)
        began = now()
        schedule = RateSchedule(
            parse_rules([{"from": "08:00", "to": "18:00", "bytes_per_s": "1M"}]),
            1000,
            now=lambda: two_to_eight + dt.timedelta(seconds=now() - began),
        )
        bucket = TokenBucket(schedule)
        await bucket.acquire(20_000, Priority.LIVE)  # goes (the bucket is full), leaving a debt of 20 s
        await bucket.acquire(100, Priority.LIVE)  # the window opens in 2 s
        assert 2.0 <= now() - began <= 2.0 + RATE_RECHECK_S

    run_virtual(main)


# --- (d) the schedule ------------------------------------------------------------------------


def fake_sysfs(root: Path, **states: str) -> Path:
    for name, state in states.items():
        (root / name).mkdir()
        (root / name / "operstate").write_text(f"{state}\n")
    return root


def at(hhmm: str) -> dt.time:
    return dt.time.fromisoformat(hhmm)


def test_time_windows_including_one_that_wraps_midnight():
    schedule = RateSchedule(
        parse_rules(
            [
                {"from": "22:00", "to": "06:00", "bytes_per_s": 100},
                {"from": "08:00", "to": "17:00", "bytes_per_s": 200},
            ]
        ),
        300,
    )
    expected = {
        "21:59:59": 300,
        "22:00": 100,
        "23:30": 100,
        "00:00": 100,
        "05:59:59": 100,
        "06:00": 300,
        "07:59": 300,
        "08:00": 200,
        "16:59:59": 200,
        "17:00": 300,
    }
    assert {t: schedule.rate_at(at(t)) for t in expected} == expected


def test_first_match_wins_and_the_default_is_the_rest():
    rules = parse_rules(
        [
            {"from": "09:00", "to": "10:00", "bytes_per_s": 0},
            {"from": "08:00", "to": "12:00", "bytes_per_s": 5000},
        ]
    )
    schedule = RateSchedule(rules, 700)
    assert schedule.rate_at(at("09:30")) is None  # the first rule: unlimited
    assert schedule.rate_at(at("10:30")) == 5000
    assert schedule.rate_at(at("13:00")) == 700
    assert RateSchedule(rules).rate_at(at("13:00")) is None
    assert RateSchedule(rules, 0).rate_at(at("13:00")) is None


def test_current_reads_the_local_time_of_day():
    clock = dt.datetime(2026, 1, 1, 23, 0)
    schedule = RateSchedule([RateRule(10, at("22:00"), at("02:00"))], 20, now=lambda: clock)
    assert schedule.current() == 10
    clock = dt.datetime(2026, 1, 2, 3, 0)
    assert schedule.current() == 20


def test_interface_rules_follow_sysfs(tmp_path: Path):
    sysfs = fake_sysfs(tmp_path, eth0="up", wlan0="down", tun0="unknown", lo="unknown", tun1="unknown")
    (sysfs / "tun0" / "carrier").write_text("1\n")
    (sysfs / "lo" / "carrier").write_text("0\n")  # tun1 has no carrier file at all

    def rate_with(interface: str) -> int | None:
        rules = parse_rules([{"interface": interface, "bytes_per_s": 0}])
        return RateSchedule(rules, 200_000, sysfs_root=sysfs).rate_at(at("12:00"))

    assert rate_with("eth0") is None  # up: the rule holds, unlimited
    assert rate_with("wlan0") == 200_000
    assert rate_with("tun0") is None  # unknown with a carrier
    assert rate_with("lo") == 200_000
    assert rate_with("tun1") == 200_000
    assert rate_with("eth9") == 200_000  # no such interface


def test_interface_and_window_together(tmp_path: Path):
    sysfs = fake_sysfs(tmp_path, eth0="up")
    rules = parse_rules([{"from": "01:00", "to": "05:00", "interface": "eth0", "bytes_per_s": 0}])
    schedule = RateSchedule(rules, 1000, sysfs_root=sysfs)
    assert schedule.rate_at(at("02:00")) is None
    assert schedule.rate_at(at("06:00")) == 1000


def test_interface_states_are_cached_for_a_second(tmp_path: Path):
    sysfs = fake_sysfs(tmp_path, eth0="up")
    clock = [50.0]
    schedule = RateSchedule(
        parse_rules([{"interface": "eth0", "bytes_per_s": 0}]), 1000, sysfs_root=sysfs, monotonic=lambda: clock[0]
    )
    assert schedule.current() is None
    (sysfs / "eth0" / "operstate").write_text("down\n")
    clock[0] += 0.9
    assert schedule.current() is None  # still the state read 0.9 s ago
    clock[0] += 0.2
    assert schedule.current() == 1000


def test_rules_from_the_toml_config_file(tmp_path: Path):
    config = tomllib.loads(
        """
        [[agent_bandwidth_rules]]
        interface = "eth0"
        bytes_per_s = 0

        [[agent_bandwidth_rules]]
        from = "22:00"
        to = 06:00:00
        bytes_per_s = "1.5MB"
        """
    )
    schedule = RateSchedule.from_config(config["agent_bandwidth_rules"], "200k", sysfs_root=tmp_path)
    assert schedule.rules == (
        RateRule(0, interface="eth0"),
        RateRule(1_500_000, start=at("22:00"), end=at("06:00")),
    )
    assert schedule.default == 200_000
    assert schedule.rate_at(at("23:00")) == 1_500_000  # eth0 is absent here
    assert schedule.rate_at(at("12:00")) == 200_000


@pytest.mark.parametrize(
    ("rule", "names"),
    [
        ({"from": "25:00", "to": "06:00", "bytes_per_s": 1}, ["field 'from'", "'25:00'", "HH:MM"]),
        ({"from": "22:00", "to": "6pm", "bytes_per_s": 1}, ["field 'to'", "'6pm'"]),
        ({"from": "22:00", "bytes_per_s": 1}, ["field 'to'", "is missing"]),
        ({"to": "06:00", "bytes_per_s": 1}, ["field 'from'", "is missing"]),
        ({"from": "06:00", "to": "06:00", "bytes_per_s": 1}, ["field 'to'", "all day"]),
        ({"from": 600, "to": "07:00", "bytes_per_s": 1}, ["field 'from'", "600"]),
        ({"interface": "eth0"}, ["field 'bytes_per_s'", "is missing"]),
        ({"bytes_per_s": -5}, ["field 'bytes_per_s'", "-5"]),
        ({"bytes_per_s": True}, ["field 'bytes_per_s'", "True"]),
        ({"bytes_per_s": 1.5}, ["field 'bytes_per_s'", "1.5"]),
        ({"bytes_per_s": "fast"}, ["field 'bytes_per_s'", "'fast'", "500k"]),
        ({"interface": "../../etc", "bytes_per_s": 1}, ["field 'interface'", "'../../etc'"]),
        ({"interface": "", "bytes_per_s": 1}, ["field 'interface'"]),
        ({"interface": "a-very-long-interface-name", "bytes_per_s": 1}, ["field 'interface'"]),
        ({"form": "22:00", "to": "06:00", "bytes_per_s": 1}, ["field 'form'", "not a rule field"]),
    ],
)
def test_a_bad_rule_is_named_with_its_field(rule: dict[str, object], names: list[str]):
    with pytest.raises(ValueError) as raised:
        parse_rules([{"bytes_per_s": 1}, rule])
    message = str(raised.value)
    assert "\n" not in message
    for name in ["bandwidth rule 2", *names]:
        assert name in message, message


def test_a_rule_that_is_not_a_table_is_named():
    with pytest.raises(ValueError, match=r"bandwidth rule 1: is a str, not a table"):
        parse_rules(["eth0"])  # type: ignore[list-item]


@pytest.mark.parametrize(
    ("text", "rate"),
    [
        ("200000", 200_000),
        ("500k", 500_000),
        ("500K", 500_000),
        ("500kB", 500_000),
        ("2M", 2_000_000),
        ("1.5MB", 1_500_000),
        ("1G", 10**9),
        ("64KiB", 65_536),
        ("2MiB", 2 * 1024**2),
        ("1GiB", 1024**3),
        (" 500 kB/s ", 500_000),
        (".5M", 500_000),
        ("0", 0),
        ("12B", 12),
    ],
)
def test_parse_rate(text: str, rate: int):
    assert parse_rate(text) == rate


@pytest.mark.parametrize("text", ["", "fast", "-5k", "5 kbit", "1e6", "5kk", "k", "1.5.5M", "9" * 400])
def test_parse_rate_refuses_what_is_not_a_rate(text: str):
    with pytest.raises(ValueError, match="rate"):
        parse_rate(text)


def test_parse_rate_refuses_a_rate_that_rounds_to_unlimited():
    with pytest.raises(ValueError, match="less than one byte per second"):
        parse_rate("0.4")
