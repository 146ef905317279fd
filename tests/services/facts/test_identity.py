"""Secret property fields (FLEET_SECRET_FIELDS) and property chunks (services/facts/identity.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.facts.identity import SecretFields, fleet_claim, read_property_chunk, words
from services.rrd.chunk import chunk_meta, decompress_payload, read_chunk
from tests.services.ingest.authed import recorded_requests
from tests.services.rrd.malformed import Seed, record_seed


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("DB_PASSWORD", ("db", "password")),
        ("apiKey", ("api", "key")),
        ("APIKey", ("api", "key")),
        ("ingest-token", ("ingest", "token")),
        ("aws.secret_access_key", ("aws", "secret", "access", "key")),
        ("AnyValues:authToken", ("any", "values", "auth", "token")),
        ("tokens_used", ("tokens", "used")),
    ],
)
def test_words(name: str, expected: tuple[str, ...]) -> None:
    assert words(name) == expected


SECRET = [
    "token",
    "ingest_token",
    "DB_PASSWORD",
    "apiKey",
    "api_key",
    "API-KEY",
    "x.api.key",
    "passwd",
    "MySecret",
    "client_secret",
    "secret_key",
    "aws_secret_access_key",
    "private_key_pem",
    "Authorization",
    "credentials",
    "auth_token",
    "authToken",
    "AnyValues:token",
    "legacy.components:Password",
]
NOT_SECRET = [
    "tokens_used",
    "robot_id",
    "host",
    "keyframe",
    "passwords_rotated_at_count",
    "tokenizer",
    "author",
    "api",
    "key",
    "accessory_key_count",
]


@pytest.mark.parametrize("name", SECRET)
def test_secret_like_names(name: str) -> None:
    assert name in SecretFields()


@pytest.mark.parametrize("name", NOT_SECRET)
def test_ordinary_names(name: str) -> None:
    assert name not in SecretFields()


def test_configured_names_replace_the_default() -> None:
    fields = SecretFields(["vin", "serial_number"])
    assert "vehicle_VIN" in fields and "serialNumber" in fields and "serial" not in fields
    assert "password" not in fields


@pytest.mark.sdk
def test_property_chunk_without_its_secrets(tmp_path: Path) -> None:
    seed = Seed.read(record_seed(tmp_path / "seed.rrd"))
    msg = seed.chunk("/__properties/fleet")
    prop = read_property_chunk(msg, chunk_meta(msg))
    assert prop.message is not msg and prop.name == "fleet"  # re-encoded without its secrets
    assert set(prop.values) == {"robot_id", "tokens_used", "tags"}
    stored = read_chunk(prop.message)
    assert {f.name for f in stored.schema} == {"rerun.controls.RowId", "robot_id", "tokens_used", "tags"}
    assert prop.message.chunk_id == msg.chunk_id  # the same chunk, stored once
    assert {c.component for c in prop.meta.components} == {"robot_id", "tokens_used", "tags"}
    custom = read_property_chunk(msg, chunk_meta(msg), SecretFields(["robot_id"]))
    assert set(custom.values) == {"ingest_token", "apiKey", "tokens_used", "tags"}


@pytest.mark.sdk
def test_the_fleet_token_is_read_and_stripped_whatever_the_secret_fields(tmp_path: Path) -> None:
    """The token an SDK stream proves itself with is read from its fleet property, and the chunk is
    filed without it even where FLEET_SECRET_FIELDS leaves `token` out."""
    recorded_requests(tmp_path / "token.rrd", "token-run", robot="r1", token="head.body.signature")
    seed = Seed.read(tmp_path / "token.rrd")
    msg = seed.chunk("/__properties/fleet")
    claim = fleet_claim(msg, chunk_meta(msg))
    assert claim is not None and (claim.token, claim.robot) == ("head.body.signature", "r1")
    assert "signature" not in repr(claim)
    prop = read_property_chunk(msg, chunk_meta(msg), SecretFields(["vin"]))
    assert prop.values == {"robot_id": "r1"}
    assert {f.name for f in read_chunk(prop.message).schema} == {"rerun.controls.RowId", "robot_id"}
    assert b"head.body.signature" in decompress_payload(msg)
    assert b"signature" not in decompress_payload(prop.message)
    info = seed.chunk("/__properties")  # RecordingInfo: no fleet property
    assert fleet_claim(info, chunk_meta(info)) is None


@pytest.mark.sdk
def test_a_fleet_property_without_a_token_claims_nothing(tmp_path: Path) -> None:
    recorded_requests(tmp_path / "robot.rrd", "robot-run", robot="r1")
    msg = Seed.read(tmp_path / "robot.rrd").chunk("/__properties/fleet")
    assert fleet_claim(msg, chunk_meta(msg)) is None
