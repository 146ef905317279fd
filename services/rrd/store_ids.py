"""Store ids of streams written before Rerun 0.25, completed from their SetStoreInfo.

Before 0.25 a `StoreId` held only a kind and a recording id: the application id was sent once,
in the `StoreInfo` of the stream's SetStoreInfo, and ArrowMsg / BlueprintActivationCommand
carried a store id without it. Newer Rerun reads such streams by remembering, per stream, the
application id of each (recording id, kind) from SetStoreInfo and filling it into the later
messages' store ids; this does the same. Only the parsed `store_id` is completed: the message
bytes are kept exactly as sent.
"""

from __future__ import annotations

import dataclasses
from typing import TypeVar

from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, StoreId, StoreInfoMessage, StoreKind

E = TypeVar("E")

_MAX_STORES = 10_000  # a stream names a handful of stores; this only bounds a hostile one


class StoreIdResolver:
    """One per stream (gRPC stream, upload or file): learns application ids from SetStoreInfo."""

    def __init__(self) -> None:
        self._application_ids: dict[tuple[StoreKind, str], str] = {}

    def learn(self, info: StoreInfoMessage) -> None:
        store = info.store_id
        if not store.application_id:
            return
        if len(self._application_ids) >= _MAX_STORES:
            self._application_ids.clear()
        self._application_ids[(store.kind, store.recording_id)] = store.application_id

    def resolve(self, store: StoreId) -> StoreId:
        """`store` with its application id, when it came without one and the stream named it."""
        if store.application_id:
            return store
        application_id = self._application_ids.get((store.kind, store.recording_id))
        return store if application_id is None else StoreId(store.kind, application_id, store.recording_id)

    def complete(self, message: E) -> E:
        """`message` with a complete store id (the same object when nothing was missing); a
        SetStoreInfo is learnt from. Any other event passes through."""
        if isinstance(message, StoreInfoMessage):
            self.learn(message)
        elif isinstance(message, ArrowMessage):
            store = self.resolve(message.store_id)
            if store is not message.store_id:
                return dataclasses.replace(message, store_id=store)  # type: ignore[return-value]
        elif isinstance(message, BlueprintActivationMessage):
            store = self.resolve(message.blueprint_id)
            if store is not message.blueprint_id:
                return dataclasses.replace(message, blueprint_id=store)  # type: ignore[return-value]
        return message
