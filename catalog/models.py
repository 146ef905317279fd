"""Catalog tables: robots, runs, and per-run entities and timelines.

The same models serve Postgres (production) and DuckDB (embedded default); types are chosen to
mean the same on both (JSON kept as text, timestamps with time zone, 64-bit integers). There are
no foreign keys: DuckDB refuses to update a row that another table references within the same
transaction, and the catalog writes a run with its entities and timelines together
(`catalog.queries.save_run`), which keeps them consistent.
"""

from __future__ import annotations

import datetime as dt

from sqlalchemy import BigInteger, Boolean, Date, DateTime, Double, Index, LargeBinary, MetaData, String, Text, func
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from core.ids import ID_LENGTH

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


class Robot(Base):
    __tablename__ = "robots"

    id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    last_seen_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class Run(Base):
    """One recording (run id = Rerun recording id), filed under robot/date/run."""

    __tablename__ = "runs"

    id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH), index=True)
    application_id: Mapped[str] = mapped_column(Text)
    date: Mapped[dt.date] = mapped_column(Date, index=True)  # UTC date of the run's start
    status: Mapped[str] = mapped_column(String(16), index=True)  # a core.states.RunStatus
    tier: Mapped[str] = mapped_column(String(16), index=True)  # a core.states.Tier
    started_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True), index=True)
    ended_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    last_data_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    sdk_version: Mapped[str | None] = mapped_column(String(64))
    chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    rows: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    properties: Mapped[str] = mapped_column(Text, default="{}")  # JSON object, secrets removed
    pinned: Mapped[bool] = mapped_column(Boolean, default=False)  # exempt from expiry: the one home of a pin
    pinned_by: Mapped[str | None] = mapped_column(String(256))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


# What a million runs need on Postgres (migration 0016, BENCHMARKS.md "A catalog of a million runs"):
# the orders runs are listed in (by start, newest first; by start within a robot; by size) and what
# retention's plan reads (runs by tier and end, within an application its policy names). A run's
# start is its `started_at`, else when the catalog first saw it: the expression `GET /v1/runs` sorts by.
Index("ix_runs_started", func.coalesce(Run.started_at, Run.created_at), Run.id)
Index("ix_runs_robot_started", Run.robot_id, func.coalesce(Run.started_at, Run.created_at), Run.id)
Index("ix_runs_bytes", Run.bytes, Run.id)
Index("ix_runs_tier_end", Run.tier, func.coalesce(Run.ended_at, Run.last_data_at))
Index("ix_runs_application_tier_end", Run.application_id, Run.tier, func.coalesce(Run.ended_at, Run.last_data_at))


class RunEntity(Base):
    __tablename__ = "run_entities"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    path: Mapped[str] = mapped_column(Text, primary_key=True)
    chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    static_chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    rows: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    archetypes: Mapped[str] = mapped_column(Text, default="[]")  # JSON list
    components: Mapped[str] = mapped_column(Text, default="[]")  # JSON list


class RunTimeline(Base):
    __tablename__ = "run_timelines"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    name: Mapped[str] = mapped_column(Text, primary_key=True)
    type: Mapped[str] = mapped_column(String(16))  # sequence | timestamp | duration
    min: Mapped[int] = mapped_column(BigInteger)
    max: Mapped[int] = mapped_column(BigInteger)


class RunLifecycle(Base):
    """Where a run's sealed objects are and what retention has done to it (one row per promoted run).

    Kept apart from `runs` so that ingest, which rewrites run rows while a run is hot, never
    touches tier state; a run's `tier` column is switched in the same transaction as this row."""

    __tablename__ = "run_lifecycle"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    prefix: Mapped[str] = mapped_column(Text)  # ROBOT/YYYY-MM-DD/RUN in the warm (and cold) store
    promoted_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    archived_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    archive_mode: Mapped[str | None] = mapped_column(String(32))  # core.states.ARCHIVED_IN_STORE or a storage class
    restore_state: Mapped[str | None] = mapped_column(String(16), index=True)  # a core.states.RestoreState
    restore_requested_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    restore_until: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    deleted_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    deleted_by: Mapped[str | None] = mapped_column(String(256))  # who: a user or "retention"
    deleted_policy: Mapped[str | None] = mapped_column(String(256))  # which policy expired it


class RunObject(Base):
    """One sealed object of a run: recording.rrd, chunks.parquet, run.json."""

    __tablename__ = "run_objects"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    key: Mapped[str] = mapped_column(Text)
    tier: Mapped[str] = mapped_column(String(16))  # Tier.WARM or Tier.COLD
    size: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))


class RetentionEvent(Base):
    """What happened to a run and why: promote, archive, restore, pin, unpin, expire, delete."""

    __tablename__ = "retention_events"
    __table_args__ = (Index("ix_retention_events_occurred_at", "occurred_at", "id"),)  # the latest first

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), index=True)
    action: Mapped[str] = mapped_column(String(16))
    occurred_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    actor: Mapped[str] = mapped_column(String(256))
    policy: Mapped[str | None] = mapped_column(String(256))
    detail: Mapped[str] = mapped_column(Text, default="")


class JobExecution(Base):
    """One execution of a scheduled job on one node (so overlaps and failures can be seen); the table
    keeps its first name, `job_runs`."""

    __tablename__ = "job_runs"
    __table_args__ = (Index("ix_job_runs_started_at", "started_at", "id"),)  # the latest first

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    job: Mapped[str] = mapped_column(String(64), index=True)
    node: Mapped[str] = mapped_column(String(256))
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    outcome: Mapped[str] = mapped_column(String(16))  # running | ok | failed
    detail: Mapped[str] = mapped_column(Text, default="")


class ApiToken(Base):
    """A token the depot signed: what it grants and whether it still does. The token itself is
    never stored, only its id (the JWT's `jti`), which every request's token is checked against."""

    __tablename__ = "tokens"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(256))
    subject: Mapped[str] = mapped_column(String(256))  # who acts with it: the actor in events and tombstones
    scopes: Mapped[str] = mapped_column(String(64))  # space-separated: ingest read write admin
    robot_id: Mapped[str | None] = mapped_column(String(ID_LENGTH))  # the one robot an ingest token writes for
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    created_by: Mapped[str] = mapped_column(String(256))
    expires_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    revoked_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    revoked_by: Mapped[str | None] = mapped_column(String(256))


class EndedSession(Base):
    """A console session ended before its time (its user logged out): its cookie, still signed and
    unexpired, is refused from then on. Kept until the cookie would have expired anyway."""

    __tablename__ = "ended_sessions"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # the session cookie's `jti`
    token_id: Mapped[str] = mapped_column(String(32))  # the token it was opened with
    ended_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    expires_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))  # the cookie's own `exp`


class Dataset(Base):
    """A dataset of Rerun's catalog protocol: the runs of one application id, which share their
    entity layout. Its entry id is a TUID (32 hex digits) that Rerun's clients keep in URLs, so it
    never changes: made when the first run of the application is catalogued, copied into each
    sealed run's run.json so that a catalog rebuild keeps it."""

    __tablename__ = "datasets"

    name: Mapped[str] = mapped_column(Text, primary_key=True)  # the application id
    entry_id: Mapped[str] = mapped_column(String(32))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))  # a run was added


class FleetTotals(Base):
    """Whole-fleet sums the console's overview shows (runs and bytes per robot and tier, objects and
    bytes per store tier), as a job last counted them: at a million runs counting them takes seconds,
    too long for each page view (`services.runs.totals`)."""

    __tablename__ = "fleet_totals"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    computed_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    runs: Mapped[int] = mapped_column(BigInteger)  # runs counted, deleted ones included
    body: Mapped[str] = mapped_column(Text)  # JSON


class DatasetColumn(Base):
    """Something a run of a dataset (an application id) has held that the dataset's segment table
    makes a column of, and how many of its runs have held it: a recording property's component with
    a kind of value, an archetype on a property entity, a timeline with its type, a metric as a number
    or as text. Counted as runs are written, moved, scrubbed and deleted (`catalog.dataset_columns`),
    so the table's schema is read from here instead of from every run; a row whose count reaches
    zero goes."""

    __tablename__ = "dataset_columns"

    application_id: Mapped[str] = mapped_column(Text, primary_key=True)
    kind: Mapped[str] = mapped_column(String(16), primary_key=True)  # property | archetype | timeline | metric
    name: Mapped[str] = mapped_column(Text, primary_key=True)
    detail: Mapped[str] = mapped_column(Text, primary_key=True)
    runs: Mapped[int] = mapped_column(BigInteger)


class Pull(Base):
    """A request that a robot's agent send the depot (part of) a run it holds: queued by an
    engineer (`origin` person) or for a trigger's window around an event (`origin` trigger: by the
    depot's live rules, or reported by the agent that fired it), polled by the agent, which reports
    its progress until done, failed, cancelled or held (kept on the robot: over its budget)."""

    __tablename__ = "pulls"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # pull- and 12 hex digits
    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), index=True)
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH), index=True)  # whose agent sends it
    include: Mapped[str] = mapped_column(Text, default="[]")  # JSON list of entity path patterns
    exclude: Mapped[str] = mapped_column(Text, default="[]")  # JSON list of entity path patterns
    timeline: Mapped[str | None] = mapped_column(Text)
    start: Mapped[str | None] = mapped_column(Text)  # as given: the agent reads it by the timeline's type
    end: Mapped[str | None] = mapped_column(Text)
    state: Mapped[str] = mapped_column(String(16))  # pending | sending | done | failed | cancelled | held
    requested_by: Mapped[str] = mapped_column(String(256))  # the token's subject, "robot R" or "trigger KIND@V"
    requested_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    chunks_sent: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes_sent: Mapped[int] = mapped_column(BigInteger, default=0)
    error: Mapped[str | None] = mapped_column(Text)
    origin: Mapped[str] = mapped_column(String(16), default="person", server_default="person")  # | trigger
    event_id: Mapped[str | None] = mapped_column(String(32), index=True)  # the event whose window it brings
    priority: Mapped[str | None] = mapped_column(String(8))  # high | normal (a trigger's pulls)


class RobotCopy(Base):
    """What a robot's agent last reported holding of a run (one row per run; gone once the robot
    deleted its copy): how much, how much of it the depot lacks, and until when it keeps it."""

    __tablename__ = "robot_copies"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH))
    reported_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    chunks: Mapped[int] = mapped_column(BigInteger, default=0)
    bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    local_only_chunks: Mapped[int] = mapped_column(BigInteger, default=0)  # held by the robot, not the depot
    local_only_bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    local_only_entities: Mapped[str] = mapped_column(Text, default="[]")  # JSON list of entity paths
    keeps_until: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))  # when the robot deletes it


class DepotNode(Base):
    """One depot process on the catalog (`fleet serve`, or one of its workers): where other nodes
    reach it, and when it last said it is alive. Its runs are its own while the heartbeat is fresh."""

    __tablename__ = "depot_nodes"

    id: Mapped[str] = mapped_column(String(256), primary_key=True)  # FLEET_NODE_ID (with -wI for workers)
    peer_addr: Mapped[str] = mapped_column(String(256))  # HOST:PORT of its peer port
    version: Mapped[str] = mapped_column(String(64))
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    heartbeat_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))  # the catalog's clock


class RunOwner(Base):
    """Which node owns a run's hot data: the one that files its chunks, serves it while hot and seals
    it. `epoch` grows at every change of owner, so a node that lost the run cannot seal it."""

    __tablename__ = "run_owners"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    node_id: Mapped[str] = mapped_column(String(256))
    epoch: Mapped[int] = mapped_column(BigInteger)
    since: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class SavedQuery(Base):
    """A SQL query saved to be drawn on the console's dashboards (as a line chart, bars or a table),
    computed again at every look so it follows the runs sealed since. Names are unique: the catalog
    checks before adding, and Postgres also holds a unique index (the embedded catalog keeps primary
    keys only, see migration 0003)."""

    __tablename__ = "saved_queries"
    __table_args__ = (Index("ix_saved_queries_name", "name", unique=True),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # q- and 12 hex digits
    name: Mapped[str] = mapped_column(String(256))
    sql: Mapped[str] = mapped_column(Text)
    chart: Mapped[str] = mapped_column(String(16))  # line | bar | table
    created_by: Mapped[str] = mapped_column(String(256))  # the token's subject, never the token
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


# --- the corpus: rules, what they make of runs, tags, webhooks ------------------------------------


class RulesVersion(Base):
    """One version of the rules file (`fleet rules apply`): its text as applied, who and when. The
    highest version is the running set; every event and metric a rule made names its version."""

    __tablename__ = "rules_versions"

    version: Mapped[int] = mapped_column(BigInteger, primary_key=True, autoincrement=False)
    text: Mapped[str] = mapped_column(Text)  # the TOML file as applied
    digest: Mapped[str] = mapped_column(String(64))  # sha256 of the text: applying the same text again is a no-op
    created_by: Mapped[str] = mapped_column(String(256))  # the token's subject, never the token
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class RunEvaluation(Base):
    """Which rules version a run's rule-made events and metrics come from, and how far: the one home
    of that fact. `final` once evaluated over the whole sealed run; a backfill evaluates every run
    whose version is not the running one."""

    __tablename__ = "run_evaluations"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    rules_version: Mapped[int] = mapped_column(BigInteger)
    state: Mapped[str] = mapped_column(String(16))  # live | final | skipped (cold: not read)
    events_capped: Mapped[bool] = mapped_column(Boolean, default=False)  # FLEET_MAX_EVENTS_PER_RUN reached
    note: Mapped[str | None] = mapped_column(Text)  # why skipped, or which rule hit the cap
    evaluated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class Event(Base):
    """A time range on a run: made by a rule (`origin` rule), by a robot (a TextLog under
    /events/**: `origin` robot), or by a person (an annotation: `origin` person). Re-evaluating a
    run replaces its rule- and robot-made events; a person's are never touched."""

    __tablename__ = "events"
    __table_args__ = (
        Index("ix_events_run_id", "run_id"),
        Index("ix_events_kind", "kind"),
        Index("ix_events_robot_id", "robot_id"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # ev- and 16 hex digits
    run_id: Mapped[str] = mapped_column(String(ID_LENGTH))
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH))
    kind: Mapped[str] = mapped_column(String(256))  # the rule's name, or the person's or robot's kind
    severity: Mapped[str] = mapped_column(String(8))  # info | warn | error
    timeline: Mapped[str] = mapped_column(String(256))
    timeline_type: Mapped[str] = mapped_column(String(16))  # timestamp (ns since epoch) | sequence | duration (ns)
    range_start: Mapped[int] = mapped_column(BigInteger)  # on `timeline`, inclusive
    range_end: Mapped[int] = mapped_column(BigInteger)  # on `timeline`, inclusive (= range_start: an instant)
    origin: Mapped[str] = mapped_column(String(8))  # rule | robot | person
    source: Mapped[str] = mapped_column(String(256))  # "rule NAME@VERSION", a token's name, or "robot"
    rules_version: Mapped[int | None] = mapped_column(BigInteger)  # rule- and robot-made events
    label: Mapped[str] = mapped_column(Text, default="")
    note: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class RunMetric(Base):
    """One value per run and metric rule: a number (`value`) or, for a property metric, text."""

    __tablename__ = "run_metrics"
    # by name, then value: a metric's runs in the order of its values (a filter, a sort)
    __table_args__ = (Index("ix_run_metrics_name_value", "name", "value", "run_id"),)

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    name: Mapped[str] = mapped_column(String(256), primary_key=True)
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH))
    value: Mapped[float | None] = mapped_column(Double)
    text_value: Mapped[str | None] = mapped_column(Text)
    rules_version: Mapped[int] = mapped_column(BigInteger)
    computed_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class RunTag(Base):
    """A freeform tag on a run, from a person (`added_by` the token's subject) or from the robot
    (the `tags` field of its `fleet` property: `added_by` "robot")."""

    __tablename__ = "run_tags"
    __table_args__ = (Index("ix_run_tags_tag", "tag"),)

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    tag: Mapped[str] = mapped_column(String(128), primary_key=True)
    added_by: Mapped[str] = mapped_column(String(256))
    added_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class Webhook(Base):
    """An endpoint told of occurrences (`event:KIND`, `event:*`, `run.sealed`, `robot.silent`) by a
    signed JSON POST. Its signing secret is kept sealed with the depot's key, never in clear."""

    __tablename__ = "webhooks"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # wh- and 12 hex digits
    url: Mapped[str] = mapped_column(Text)
    subscriptions: Mapped[str] = mapped_column(Text)  # JSON list of what it is told of
    body_format: Mapped[str] = mapped_column(String(16))  # json | slack
    secret_sealed: Mapped[str] = mapped_column(Text)  # the HMAC secret, encrypted with the depot's key
    created_by: Mapped[str] = mapped_column(String(256))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class WebhookDelivery(Base):
    """One occurrence to tell one webhook of, written in the transaction that made the occurrence
    (an outbox): at most one per webhook and occurrence, retried with backoff until delivered or a
    day has passed."""

    __tablename__ = "webhook_deliveries"
    __table_args__ = (Index("ix_webhook_deliveries_webhook_id", "webhook_id"),)

    id: Mapped[str] = mapped_column(String(64), primary_key=True)  # webhook id + ":" + occurrence id
    webhook_id: Mapped[str] = mapped_column(String(32))
    occurrence: Mapped[str] = mapped_column(String(256))  # e.g. event:intervention, run.sealed
    body: Mapped[str] = mapped_column(Text)  # the JSON body as sent
    state: Mapped[str] = mapped_column(String(16))  # pending | delivered | failed (gave up)
    attempts: Mapped[int] = mapped_column(BigInteger, default=0)
    next_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    last_status: Mapped[int | None] = mapped_column(BigInteger)  # the endpoint's HTTP status
    last_error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    delivered_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))


# --- dataset snapshots: a selection of runs resolved into an immutable list of episodes ----------


class DatasetSnapshot(Base):
    """A named dataset snapshot (`fleet datasets create NAME`), whose versions are its resolutions.
    Not `Dataset`, which is a dataset of Rerun's catalog protocol (an application id)."""

    __tablename__ = "dataset_snapshots"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    created_by: Mapped[str] = mapped_column(String(256))  # who made its first version
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class DatasetVersion(Base):
    """One immutable version `NAME@VERSION`: the selection as given (canonical JSON), who resolved it
    and when, the rules version running then, and what it came to."""

    __tablename__ = "dataset_versions"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    version: Mapped[int] = mapped_column(BigInteger, primary_key=True, autoincrement=False)
    selection: Mapped[str] = mapped_column(Text)  # canonical JSON (sorted keys)
    created_by: Mapped[str] = mapped_column(String(256))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    rules_version: Mapped[int | None] = mapped_column(BigInteger)  # None: no rules applied then
    episodes: Mapped[int] = mapped_column(BigInteger)
    runs: Mapped[int] = mapped_column(BigInteger)  # distinct runs with an episode
    chunks: Mapped[int] = mapped_column(BigInteger)  # summed over episodes (a chunk two windows share counts twice)
    bytes: Mapped[int] = mapped_column(BigInteger)  # as chunks
    skipped: Mapped[str] = mapped_column(Text)  # JSON: [{"run", "why"}] runs the selection matched but could not read


class DatasetEpisode(Base):
    """An episode of a version: a run, whole (no range) or a window around one of its events, and
    the chunks it reads."""

    __tablename__ = "dataset_episodes"
    __table_args__ = (Index("ix_dataset_episodes_run_id", "run_id"),)

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    version: Mapped[int] = mapped_column(BigInteger, primary_key=True, autoincrement=False)
    episode: Mapped[int] = mapped_column(BigInteger, primary_key=True, autoincrement=False)  # 0, 1, ...
    run_id: Mapped[str] = mapped_column(String(ID_LENGTH))
    robot_id: Mapped[str] = mapped_column(String(ID_LENGTH))
    split: Mapped[str | None] = mapped_column(String(32))
    timeline: Mapped[str] = mapped_column(String(256))
    range_start: Mapped[int | None] = mapped_column(BigInteger)  # inclusive; None (both): the whole run
    range_end: Mapped[int | None] = mapped_column(BigInteger)  # inclusive
    event_id: Mapped[str | None] = mapped_column(String(32))  # the event the window is around
    chunk_ids: Mapped[bytes] = mapped_column(LargeBinary)  # the sorted 16-byte ids, concatenated
    chunks: Mapped[int] = mapped_column(BigInteger)
    bytes: Mapped[int] = mapped_column(BigInteger)  # the sum of their frames' lengths in the recording


class DatasetExport(Base):
    """A job writing a snapshot version in a training format (`fleet datasets export`): queued,
    claimed by a depot process that beats a heartbeat while it runs it, done, failed or cancelled;
    its progress, and the quality flags of each flagged or skipped episode (`report`, JSON)."""

    __tablename__ = "dataset_exports"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # exp- and 12 hex digits
    name: Mapped[str] = mapped_column(String(64))
    version: Mapped[int] = mapped_column(BigInteger)
    format: Mapped[str] = mapped_column(String(16))  # lerobot
    spec: Mapped[str] = mapped_column(Text)  # JSON: what goes where, checks' limits, strict
    target: Mapped[str] = mapped_column(Text)  # file:///PATH or s3://BUCKET/PREFIX
    state: Mapped[str] = mapped_column(String(16))  # queued | running | done | failed | cancelled
    episodes: Mapped[int] = mapped_column(BigInteger)
    done: Mapped[int] = mapped_column(BigInteger)
    frames: Mapped[int] = mapped_column(BigInteger)
    skipped: Mapped[int] = mapped_column(BigInteger)
    flagged: Mapped[int] = mapped_column(BigInteger)
    bytes: Mapped[int] = mapped_column(BigInteger)  # written to the target
    report: Mapped[str] = mapped_column(Text)  # JSON: [{"episode", "run", "exported_as", "frames", "flags"}]
    error: Mapped[str | None] = mapped_column(Text)
    created_by: Mapped[str] = mapped_column(String(256))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    node: Mapped[str | None] = mapped_column(String(256))  # the process running it
    heartbeat_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))


class Import(Base):
    """One upload, RRD or MCAP, from its first byte to its end: receiving, converting (MCAP), filed or
    failed with why. An MCAP import keeps its file's content digest (its identity: conversion makes
    fresh chunk ids each time) and the digest of its data section up to `data_end` (where its summary
    begins), which says whether a later bag extends it. A failed MCAP's original waits in the
    quarantine prefix until `quarantine_until`."""

    __tablename__ = "imports"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)  # imp- and 12 hex digits
    kind: Mapped[str] = mapped_column(String(8))  # rrd | mcap
    state: Mapped[str] = mapped_column(String(16))  # receiving | converting | filed | failed
    name: Mapped[str] = mapped_column(String(256))  # the file's name as the client gave it, or ""
    bytes: Mapped[int] = mapped_column(BigInteger)  # received
    robot_id: Mapped[str | None] = mapped_column(String(ID_LENGTH))
    run_ids: Mapped[str] = mapped_column(Text)  # JSON list: the runs it filed into
    application_id: Mapped[str | None] = mapped_column(String(256))
    chunks_new: Mapped[int] = mapped_column(BigInteger)
    chunks_duplicate: Mapped[int] = mapped_column(BigInteger)
    reason: Mapped[str | None] = mapped_column(Text)  # why it failed, or what it was (already held)
    digest: Mapped[str | None] = mapped_column(String(64))  # sha256 of an MCAP file
    head_digest: Mapped[str | None] = mapped_column(String(64))  # sha256 of its first HEAD_BYTES
    data_end: Mapped[int | None] = mapped_column(BigInteger)  # where its summary section begins
    data_digest: Mapped[str | None] = mapped_column(String(64))  # sha256 of its bytes before data_end
    held_by: Mapped[str | None] = mapped_column(String(32))  # the import that already held this file
    converter: Mapped[str | None] = mapped_column(String(64))  # the rerun CLI version that converted it
    quarantine_key: Mapped[str | None] = mapped_column(Text)
    quarantine_until: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    node: Mapped[str | None] = mapped_column(String(256))
    created_by: Mapped[str] = mapped_column(String(256))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True))


class McapDigest(Base):
    """An MCAP file the depot holds or is converting, by content digest: one row per file, so two
    uploads of one bag at once cannot both file it (the second insert fails)."""

    __tablename__ = "mcap_digests"

    digest: Mapped[str] = mapped_column(String(64), primary_key=True)
    import_id: Mapped[str] = mapped_column(String(32))
    run_id: Mapped[str] = mapped_column(String(ID_LENGTH))


class LakehouseRun(Base):
    """A run's rows in the lakehouse's Iceberg tables (`services.lakehouse`): `wanted` counts the
    changes writers marked (its sealing, analytics files, metrics, events, tags, tier, deletion),
    `synced` the change the tables hold; `telemetry`: its analytics files changed too (their rows
    are copied again, not only its catalog rows). One row per run ever sent there."""

    __tablename__ = "lakehouse_runs"

    run_id: Mapped[str] = mapped_column(String(ID_LENGTH), primary_key=True)
    wanted: Mapped[int] = mapped_column(BigInteger)
    synced: Mapped[int] = mapped_column(BigInteger)
    pending: Mapped[bool] = mapped_column(Boolean)
    telemetry: Mapped[bool] = mapped_column(Boolean)
    synced_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    rows: Mapped[int] = mapped_column(BigInteger, default=0)  # telemetry rows the tables hold for it


# What the sync job reads: the few pending runs among all (Postgres; the embedded catalog keeps
# primary keys only, see migration 0003).
Index("ix_lakehouse_runs_pending", LakehouseRun.run_id, postgresql_where=LakehouseRun.pending)
