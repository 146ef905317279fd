"""The ownership pass (many depot nodes on one catalog), every few seconds on every node.

- Runs hot here: a lease the catalog no longer shows (another node took the run over while this
  one did not heart-beat) is dropped; a lease the catalog shows but this node did not know of (it
  restarted, or claimed the run when the catalog answered again) is taken up.
- Closed hot runs this node holds without a lease (filed while the catalog did not answer, or
  taken over from it) are claimed if nobody else owns them, else handed to their owner over its
  peer port, whole, and removed here once the owner has filed them (it skips chunks it holds).
- Leases of runs this node no longer holds hot and no open source is filing are given up.
Each step is safe to repeat: a hand-over that breaks is sent again whole at the next pass.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass, field

from services.auth.tokens import Auth
from services.cluster.ownership import Lease, Ownership
from services.cluster.relay import PEER_CREDENTIAL, RELAYED_BY, SOURCE_KIND, hand_over
from services.hot.read import read_events
from services.ingest.service import IngestService
from services.ingest.view import HotRunView

log = logging.getLogger(__name__)

HAND_OVER_TIMEOUT_S = 600.0


@dataclass
class PassReport:
    adopted: list[str] = field(default_factory=list)
    lost: list[str] = field(default_factory=list)
    claimed: list[str] = field(default_factory=list)
    handed_over: list[str] = field(default_factory=list)
    released: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)


def ownership_pass(ingest: IngestService, auth: Auth | None) -> PassReport:
    ownership = ingest.ownership
    report = PassReport()
    if ownership is None:
        return report
    leases = ownership.leases()
    _match_leases(ingest, leases, report)
    for run in ingest.closed_runs():
        if run.lease is None:
            try:
                _settle(run, ingest, ownership, auth, report)
            except Exception as exc:  # the next pass tries again
                report.failed[run.run_id] = f"{type(exc).__name__}: {exc}"
                log.warning("run %s not handed to its owner yet: %s", run.run_id, report.failed[run.run_id])
    for run_id, epoch in leases.items():
        idle = ingest.hot_run(run_id) is None and ingest.open_claims.get(run_id, 0) <= 0
        if idle and ownership.release(Lease(run_id, epoch), idle=True):
            report.released.append(run_id)
    return report


def _match_leases(ingest: IngestService, leases: dict[str, int], report: PassReport) -> None:
    for run in ingest.hot_runs():
        epoch = leases.get(run.run_id)
        if run.lease is not None and epoch != run.lease.epoch:
            log.warning("run %s was taken over by another node: its hot copy here goes to that node", run.run_id)
            ingest.lose_lease(run.run_id)
            report.lost.append(run.run_id)
        elif run.lease is None and epoch is not None:
            ingest.take_lease(run.run_id, Lease(run.run_id, epoch))
            report.adopted.append(run.run_id)


def _settle(
    run: HotRunView, ingest: IngestService, ownership: Ownership, auth: Auth | None, report: PassReport
) -> None:
    got = ownership.claim(run.run_id)
    if isinstance(got, Lease):
        ingest.take_lease(run.run_id, got)  # its owner now: its catalog row is written, and it is promoted
        report.claimed.append(run.run_id)
        return
    token = auth.peer_token(ownership.node_id, run.robot_id or run.started_by) if auth is not None else None
    metadata = [(RELAYED_BY, ownership.node_id), (SOURCE_KIND, "upload")]
    if token is not None:  # the owner files it as this node's (write scope), and believes who relays it
        metadata += [("authorization", f"Bearer {token}"), (PEER_CREDENTIAL, token)]
    answer = hand_over(got, read_events(run.path, run.size), metadata, HAND_OVER_TIMEOUT_S)
    left = ingest.hand_over(run, doing="being handed over", then="handed over again")
    shutil.rmtree(left.folder, ignore_errors=True)
    report.handed_over.append(run.run_id)
    log.info(
        "hot copy of run %s handed to node %s, which owns it (%s new chunks, %s it held) and removed here",
        run.run_id,
        got.node_id,
        answer.get("chunks_new", "?"),
        answer.get("chunks_duplicate", "?"),
    )
