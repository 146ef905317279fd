"""Signed links over REST: asked for with a read token, opened with no header, refused (403) when
changed, expired or when the token that asked was revoked; every refusal counted in /metrics."""

from __future__ import annotations

import datetime as dt
import socket
from collections.abc import Callable
from urllib.parse import parse_qsl, urlencode, urlsplit

import pytest

from services.auth.tokens import FORBIDDEN
from tests.services.auth.conftest import Depot, bearer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

RUN = "rec-points"
FILTERS = [("include", "/world/points"), ("timeline", "frame"), ("start", "102"), ("end", "104")]


@pytest.fixture
def uploaded(depot: Depot, scenes: dict[str, Recording]) -> Depot:
    answer = depot.client.post("/v1/uploads", content=scenes["points"].data, headers=bearer(depot.token("write")))
    assert answer.status_code == 200, answer.text
    return depot


def _link(depot: Depot, token: str, params: list[tuple[str, str]] = FILTERS, **extra: str) -> str:
    answer = depot.client.post(f"/v1/runs/{RUN}/links", params=[*params, *extra.items()], headers=bearer(token))
    assert answer.status_code == 200, answer.text
    url: str = answer.json()["url"]
    return url


Params = list[tuple[str, str]]


def _with(url: str, run: str = RUN, change: Callable[[Params], Params] = lambda params: params) -> str:
    parts = urlsplit(url)
    path = parts.path.replace(f"/v1/runs/{RUN}/", f"/v1/runs/{run}/")
    return f"{parts.scheme}://{parts.netloc}{path}?{urlencode(change(parse_qsl(parts.query)))}"


def test_a_signed_link_downloads_what_the_token_would(uploaded: Depot):
    reader = uploaded.token("read")
    answer = uploaded.client.post(f"/v1/runs/{RUN}/links", params=FILTERS, headers=bearer(reader))
    link = answer.json()
    # the test client's Host (testserver) is none of the depot's names: the base is the bind address
    bound = f"http://{socket.gethostname()}:8080/v1/runs/rec-points/recording.rrd?"
    assert link["run"] == RUN and link["url"].startswith(bound)
    expires = dt.datetime.fromisoformat(link["expires_at"])
    assert dt.timedelta(hours=23) < expires - dt.datetime.now(dt.UTC) <= dt.timedelta(hours=24)  # FLEET_LINK_TTL_S

    opened = uploaded.client.get(link["url"])  # no header
    assert opened.status_code == 200, opened.text
    with_header = uploaded.client.get(f"/v1/runs/{RUN}/recording.rrd", params=FILTERS, headers=bearer(reader))
    assert with_header.status_code == 200 and opened.content == with_header.content
    whole = uploaded.client.get(f"/v1/runs/{RUN}/recording.rrd", headers=bearer(reader))
    assert len(whole.content) > len(opened.content)  # the filters were applied, not dropped
    assert opened.content.startswith(b"RRF2")


def test_a_link_asks_for_a_read_token_and_an_existing_run(uploaded: Depot):
    no_token = uploaded.client.post(f"/v1/runs/{RUN}/links", params=FILTERS)
    assert no_token.status_code == 401
    missing = uploaded.client.post("/v1/runs/no-such-run/links", headers=bearer(uploaded.token("read")))
    assert missing.status_code == 404
    unknown = uploaded.client.post(f"/v1/runs/{RUN}/links?color=red", headers=bearer(uploaded.token("read")))
    assert unknown.json()["code"] == "INVALID_ARGUMENT" and "color" in unknown.json()["message"]


def _replace(key: str, value: str) -> Callable[[Params], Params]:
    return lambda params: [(k, value if k == key else v) for k, v in params]


TAMPERED = {
    "param changed": lambda url: _with(url, change=_replace("include", "/**")),
    "window widened": lambda url: _with(url, change=_replace("end", "105")),
    "param added": lambda url: _with(url, change=lambda p: [*p, ("exclude", "/world/sparse")]),
    "param removed": lambda url: _with(url, change=lambda p: [x for x in p if x[0] != "start"]),
    "run changed": lambda url: _with(url, run="rec-other"),
    "signature changed": lambda url: _with(url, change=_replace("sig", "0" * 64)),
    "signature not hex": lambda url: _with(url, change=_replace("sig", "é" * 64)),
    "signature dropped": lambda url: _with(url, change=lambda p: [x for x in p if x[0] != "sig"]),
    "expiry pushed": lambda url: _with(url, change=_replace("expires", "4102444800")),
}


def test_a_tampered_link_is_refused_and_counted(uploaded: Depot):
    url = _link(uploaded, uploaded.token("read"))
    before = uploaded.failures("link", FORBIDDEN)
    for what, tamper in TAMPERED.items():
        answer = uploaded.client.get(tamper(url))
        if what == "signature dropped":  # no longer a link: a request without a token
            assert answer.status_code == 401, (what, answer.text)
            continue
        assert answer.status_code == 403, (what, answer.text)
        assert answer.json()["code"] == "PERMISSION_DENIED" and "ask for a new" in answer.json()["message"]
    assert uploaded.failures("link", FORBIDDEN) == before + len(TAMPERED) - 1
    assert uploaded.client.get(url).status_code == 200  # the link itself still opens


def test_an_expired_link_is_refused(uploaded: Depot):
    # Expiry times are whole seconds: a one-second link may be gone a moment after it is made.
    url = _link(uploaded, uploaded.token("read"), expires_in="60")
    assert uploaded.client.get(url).status_code == 200
    real = uploaded.auth.clock
    uploaded.auth.clock = lambda: real() + dt.timedelta(seconds=61)
    answer = uploaded.client.get(url)
    assert answer.status_code == 403 and "expired" in answer.json()["message"], answer.text


def test_the_links_of_a_revoked_token_are_refused(uploaded: Depot):
    issued = uploaded.issue("read", name="colleague")
    url = _link(uploaded, issued.token)
    assert uploaded.client.get(url).status_code == 200
    revoked = uploaded.client.delete(f"/v1/tokens/{issued.record.id}", headers=bearer(uploaded.token("admin")))
    assert revoked.status_code == 200
    before = uploaded.failures("link", FORBIDDEN)
    answer = uploaded.client.get(url)
    assert answer.status_code == 403 and "revoked" in answer.json()["message"], answer.text
    assert uploaded.failures("link", FORBIDDEN) == before + 1


def test_a_link_with_a_header_is_checked_as_the_header(uploaded: Depot):
    """A client that sends a token is judged by it, not by a link it also carries."""
    url = _link(uploaded, uploaded.token("read"))
    assert uploaded.client.get(url, headers=bearer(uploaded.token("read"))).status_code == 200
    robot = uploaded.token("ingest", robot="robot-a")
    assert uploaded.client.get(url, headers=bearer(robot)).status_code == 403
