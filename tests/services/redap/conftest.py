"""Shared pieces of the catalog-server tests: Rerun's own `rerun server` on given recordings, and the
depot's scenes (depots.SCENES) served by `fleet serve` and by Rerun's server alike, once per test
session for the tests that only read them."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from tests.services.ingest.live_server import LiveServer
from tests.services.redap.client import Redap, reference_serving
from tests.services.redap.depots import SCENES, reference_datasets, serving
from tests.services.rrd.recordings import Recording

ReferenceServer = Callable[[dict[str, list[Recording]]], Redap]


@pytest.fixture
def reference_server(rerun_bin: str, tmp_path: Path) -> Iterator[ReferenceServer]:
    """Start Rerun's own `rerun server -d NAME=DIR` on the given recordings (a dataset per name);
    returns a `Redap` client of it. Stopped at the end of the test."""
    numbers = itertools.count()
    with ExitStack() as started:

        def start(datasets: dict[str, list[Recording]]) -> Redap:
            folder = tmp_path / f"reference-{next(numbers)}"
            files = {name: [rec.path for rec in recs] for name, recs in datasets.items()}
            return started.enter_context(reference_serving(rerun_bin, folder, files))

        yield start


@pytest.fixture(scope="session")
def scenes(recordings: dict[str, Recording]) -> dict[str, Recording]:
    """The scenes a depot of these tests holds, from the session's recordings."""
    return {name: recordings[name] for name in SCENES}


@pytest.fixture(scope="session")
def served(scenes: dict[str, Recording], tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """`fleet serve` holding the scenes (depots.serving); tests only read it."""
    with serving(scenes, tmp_path_factory.mktemp("redap-depot") / "data") as server:
        yield server


@pytest.fixture
def served_client(served: LiveServer) -> Iterator[Redap]:
    client = Redap(served.grpc_port)
    yield client
    client.close()


@pytest.fixture(scope="session")
def scenes_reference(
    rerun_bin: str, scenes: dict[str, Recording], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Redap]:
    """Rerun's own server on the same scenes, a dataset per application id; tests only read it."""
    folder = tmp_path_factory.mktemp("redap-reference")
    files = {name: [rec.path for rec in recs] for name, recs in reference_datasets(scenes).items()}
    with reference_serving(rerun_bin, folder, files) as client:
        yield client
