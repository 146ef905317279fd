"""TUIDs: Rerun's 128-bit ids (nanoseconds, then a counter), which its clients require of entry
ids. Written as Rerun writes them: 16 upper-case hex digits of the time, 16 lower-case of the
counter (`18EA6CA8C3020B3029d1569232672548`)."""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass

from core.clock import aware
from core.errors import InvalidArgumentError
from services.rrd.pb import common_pb2

_TEXT = re.compile(r"^[0-9A-Fa-f]{32}$")
_MASK = (1 << 64) - 1
EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)


def epoch_ns(moment: dt.datetime) -> int:
    """Nanoseconds since the epoch, exactly (a float's 53 bits would round today's times)."""
    delta = aware(moment) - EPOCH
    return (delta.days * 86400 + delta.seconds) * 10**9 + delta.microseconds * 1000


@dataclass(frozen=True, order=True)
class Tuid:
    time_ns: int
    inc: int

    def __str__(self) -> str:
        return f"{self.time_ns:016X}{self.inc:016x}"

    def to_bytes(self) -> bytes:
        """Big-endian, time first: Arrow's `fixed_size_binary[16]` form in Rerun's tables."""
        return self.time_ns.to_bytes(8, "big") + self.inc.to_bytes(8, "big")

    def to_proto(self) -> common_pb2.Tuid:
        return common_pb2.Tuid(time_ns=self.time_ns, inc=self.inc)

    def entry_id(self) -> common_pb2.EntryId:
        return common_pb2.EntryId(id=self.to_proto())

    @classmethod
    def parse(cls, text: str) -> Tuid:
        """From its 32 hex digits; INVALID_ARGUMENT naming the form otherwise."""
        if not _TEXT.match(text):
            raise InvalidArgumentError(
                f"{text[:64]!r} is not an entry id: expected 32 hex digits, as the catalog lists them"
            )
        return cls(int(text[:16], 16), int(text[16:], 16))

    @classmethod
    def from_proto(cls, tuid: common_pb2.Tuid) -> Tuid:
        return cls(tuid.time_ns & _MASK, tuid.inc & _MASK)
