"""Which node files a source's runs (see docs/scale-out.md).

At a recording's SetStoreInfo, before anything of it is filed, ingest asks the catalog who owns the
run (`Ownership.claim`): this node (it had no owner, or its owner stopped heart-beating), or another
node that is alive. A source whose first recording another node owns is relayed there whole, byte
for byte; a catalog that does not answer in time leaves the run filed here without a lease, and it
is handed to its owner later (as is a second recording of a source that another node owns, and
anything a relayed source brings: the owner files it and never relays again).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Iterable
from typing import TYPE_CHECKING, Any

from core.errors import UnavailableError
from services.auth.scopes import Principal
from services.auth.tokens import Auth
from services.cluster.ownership import Lease, Owner
from services.cluster.relay import PEER_CREDENTIAL, RELAYED_BY, SOURCE_KIND, PeerUnavailable, Relay, request_of
from services.ingest.source import Source
from services.ingest.stream_auth import Metadata
from services.rrd.messages import Event

if TYPE_CHECKING:
    from services.ingest.service import IngestService

log = logging.getLogger(__name__)


async def route(service: IngestService, source: Source, run_id: str) -> None:
    """Settle who files `run_id` for this source: `source.leases` (here) or `source.relay_to`."""
    ownership = service.ownership
    if ownership is None or run_id in source.routed:
        return
    source.routed.add(run_id)
    run = service.runs.get(run_id)
    if run is not None and not run.handed_over and run.lease is not None:
        source.leases[run_id] = run.lease
        service.open_claims[run_id] += 1
        return
    service.open_claims[run_id] += 1  # before asking: the ownership pass keeps a lease being claimed
    try:
        got = await asyncio.wait_for(asyncio.to_thread(ownership.claim, run_id), service.lookup_timeout_s)
    except Exception as exc:  # the catalog is down or slow: filed here, handed to its owner later
        log.warning("could not ask the catalog who owns run %s (%s): filed here for now", run_id, type(exc).__name__)
        return
    if isinstance(got, Lease):
        source.leases[run_id] = got
        if run is not None and not run.handed_over and run.lease is None:
            run.lease = got
        return
    if source.relayed_by is None and source.recording_run is None:
        source.relay_to = got
    else:
        log.info("run %s is owned by node %s: filed here, handed over when it closes", run_id, got.node_id)


def relay_metadata(service: IngestService, auth: Auth, source: Source, metadata: Metadata) -> list[tuple[str, str]]:
    """The caller's own credentials (the owner checks them as this node did), who relays, and this
    node's peer token, which makes the owner believe that (it grants nothing: no scope)."""
    assert service.ownership is not None
    node = service.ownership.node_id
    passed = [(k, str(v)) for k, v in metadata or () if k == "authorization"]
    relayed = [*passed, (RELAYED_BY, node), (SOURCE_KIND, "live" if source.live else "upload")]
    token = auth.peer_token(node, None, ())
    return [*relayed, (PEER_CREDENTIAL, token)] if token is not None else relayed


async def open_relay(service: IngestService, auth: Auth, source: Source, metadata: Metadata) -> Relay | None:
    """A relay to the owner of the source's run; None if this node has since taken the run over (its
    owner stopped answering and its lease ran out: then the source is filed here). UNAVAILABLE if
    the owner neither answers nor lets its lease run out in time."""
    ownership, owner = service.ownership, source.relay_to
    assert ownership is not None and owner is not None and service.channels is not None
    loop = asyncio.get_running_loop()
    deadline = loop.time() + ownership.lease_s * 2 + 5
    while True:
        try:
            relay = await Relay.open(service.channels, owner, relay_metadata(service, auth, source, metadata))
        except PeerUnavailable:
            if loop.time() > deadline:
                raise UnavailableError(
                    f"node {owner.node_id}, which owns run {owner.run_id}, does not answer at {owner.peer_addr} "
                    "and still holds its lease: send again in a few seconds"
                ) from None
        else:
            source.relay_to = None
            return relay
        await asyncio.sleep(min(1.0, ownership.lease_s / 4))  # the owner's lease runs out on the catalog's clock
        got = await asyncio.to_thread(ownership.claim, owner.run_id)
        if isinstance(got, Lease):
            source.leases[owner.run_id], source.relay_to = got, None
            return None
        owner = source.relay_to = got


async def relay_source(
    service: IngestService,
    auth: Auth,
    source: Source,
    metadata: Metadata,
    first: Iterable[Event],
    more: AsyncIterator[bytes],
) -> dict[str, Any] | None:
    """Send the rest of a source to its run's owner: what it held back, the events `first`, then
    every request `more` brings; the owner's answer (what it filed). None if this node took the run
    over meanwhile: then it files the source itself. A stream and an upload alike."""
    relay = await open_relay(service, auth, source, metadata)
    if relay is None:
        return None
    try:
        await relay_held(relay, source)
        for event in first:
            if (request := request_of(event)) is not None:
                await relay.send(request)
        async for request in more:
            await relay.send(request)
        return await relay.finish()
    except BaseException:
        relay.cancel()
        raise


async def relay_held(relay: Relay, source: Source) -> None:
    """What the source held back before its run was routed (blueprints that came first)."""
    held, source.held, source.held_bytes = source.held, [], 0
    for _, event in held:
        request = request_of(event)
        if request is not None:
            await relay.send(request)


async def owner_elsewhere(service: IngestService, run_id: str) -> Owner | None:
    """Another live node that owns the run while this one holds nothing of it hot: reads of the
    run's hot data are asked of that node."""
    if service.ownership is None or service.hot_run(run_id) is not None:
        return None
    return await asyncio.to_thread(service.ownership.owner_elsewhere, run_id)


async def owner_down(service: IngestService, run_id: str) -> Owner | None:
    """Another node that owns the run and has stopped heart-beating, while this one holds nothing
    of it hot: what a read of it that found nothing here is waiting for."""
    if service.ownership is None or service.hot_run(run_id) is not None:
        return None
    return await asyncio.to_thread(service.ownership.owner_down, run_id)


def asking_for(service: IngestService, auth: Auth, principal: Principal) -> list[tuple[str, str]]:
    """Metadata for asking the owner on behalf of `principal` (checked here): a short-lived token of
    this node with the caller's scopes and robot."""
    assert service.ownership is not None
    token = auth.peer_token(service.ownership.node_id, principal.robot, principal.scopes)
    return [("authorization", f"Bearer {token}")] if token is not None else []
