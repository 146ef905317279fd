"""Datasets and segments as the catalog holds them: a dataset is an application id (its entry id a
TUID in the `datasets` table), a segment one of its runs."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from catalog import queries
from catalog.models import Dataset, Run
from core.errors import NotFoundError
from core.states import Tier
from services.redap.tuid import Tuid


def dataset_by_entry(session: Session, entry: Tuid) -> Dataset:
    """The dataset an `x-rerun-entry-id` names; NOT_FOUND naming how to list them."""
    found = session.scalars(select(Dataset).where(Dataset.entry_id == str(entry))).first()
    if found is None:
        raise NotFoundError(f"no dataset has entry id {entry}: list the catalog's entries (FindEntries) for their ids")
    return found


def segment_run(session: Session, dataset: Dataset, segment_id: str) -> Run:
    """The run a segment id names, if it is one of the dataset's; NOT_FOUND otherwise."""
    run = queries.get_run(session, segment_id)
    if run is None or run.application_id != dataset.name:
        raise NotFoundError(f"dataset {dataset.name!r} has no segment {segment_id!r}")
    return run


def dataset_runs(session: Session, dataset: Dataset) -> list[Run]:
    """The dataset's runs that still hold data (deleted runs keep a tombstone row, not a segment)."""
    return list(
        session.scalars(
            select(Run).where(Run.application_id == dataset.name, Run.tier != Tier.DELETED).order_by(Run.id)
        )
    )
