"""The client-version gate: Rerun clients outside the tested range are told which to install."""

from __future__ import annotations

import pytest

from core.errors import ConflictError
from services.redap.clients import NEWEST, OLDEST, check_client


@pytest.mark.parametrize(
    "version", [f"rerun/{NEWEST[0]}.{NEWEST[1]}.0", f"rerun-py/{OLDEST[0]}.{OLDEST[1]}.2", "rerun-py/0.41.0-rc.1"]
)
def test_clients_in_the_tested_range_pass(version: str):
    check_client([("x-rerun-client-version", version)])


@pytest.mark.parametrize("version", ["rerun-py/0.30.2", f"rerun/{NEWEST[0]}.{NEWEST[1] + 1}.0", "rerun/1.0.0"])
def test_clients_outside_it_are_told_the_range(version: str):
    with pytest.raises(ConflictError) as refused:
        check_client([("x-rerun-client-version", version)])
    message = str(refused.value)
    assert f"{OLDEST[0]}.{OLDEST[1]}" in message and f"rerun-sdk=={NEWEST[0]}.{NEWEST[1]}.*" in message


def test_calls_without_a_rerun_version_pass():
    check_client([("user-agent", "grpc-python")])
    check_client([("x-rerun-client-version", "something else")])
    check_client(None)
