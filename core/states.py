"""The closed sets of states a run (and a pull of one) can be in, defined once.

They are `StrEnum`s: each member is its string, so the catalog columns (plain strings), the JSON
answers, the CLI's choices and `run.json` hold the same values as before there were enums, and a
value read back from the catalog as a plain string compares equal to its member.
"""

from __future__ import annotations

from enum import StrEnum


class RunStatus(StrEnum):
    """Whether a stream still feeds the run (`runs.status`)."""

    LIVE = "live"
    CLOSED = "closed"


class Tier(StrEnum):
    """Where a run's recording is (`runs.tier`; a sealed object's `run_objects.tier` is warm or cold)."""

    HOT = "hot"  # files on the disk of the node that ingested it
    WARM = "warm"  # sealed, in the warm store
    COLD = "cold"  # sealed and archived: in the cold store, or in an archive storage class
    DELETED = "deleted"  # its objects are gone; the catalog keeps a tombstone


class RestoreState(StrEnum):
    """How far a cold run's restore has got (`run_lifecycle.restore_state`; none: not asked for)."""

    RESTORING = "restoring"
    RESTORED = "restored"


# `run_lifecycle.archive_mode` of a recording copied to the cold store; any other mode is the S3
# storage class it was moved to in place (an open set, so not an enum).
ARCHIVED_IN_STORE = "store"


class PullState(StrEnum):
    """How far a robot's agent has got with a pull (`pulls.state`): pending until it starts sending,
    then done or failed; cancelled by whoever asked, while pending or sending. Held: the agent keeps
    the window on the robot (a trigger's window over its trigger's budget), until a person cancels it
    (dismissed) or pulls it again."""

    PENDING = "pending"
    SENDING = "sending"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"
    HELD = "held"
