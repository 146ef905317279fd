"""The webhook routes through the app as `fleet serve` wires it, with auth on, called with the REST
client the CLI uses: admin only, the secret in the creation's answer alone, and every refusal a 4xx
that says why."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from sdk_client.rest import FleetClient, ServiceError
from tests.services.auth.conftest import Depot, open_depot

DEPOT_PORT = 18080  # the REST port the depot's settings give (TestClient binds none)


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    allowed = '["127.0.0.1", "169.254.169.254"]'
    with open_depot(tmp_path, fresh_catalog_url, webhook_hosts=allowed, http_addr=f"127.0.0.1:{DEPOT_PORT}") as opened:
        yield opened


def sdk(depot: Depot, token: str | None) -> FleetClient:
    fleet = FleetClient("http://testserver", token=token)
    fleet.close()
    fleet._http = TestClient(depot.app, base_url="http://testserver", headers=dict(fleet._http.headers))
    return fleet


def refused(call: Callable[[], Any], status: int, *says: str) -> None:
    with pytest.raises(ServiceError) as info:
        call()
    assert info.value.status == status, info.value.body
    for text in says:
        assert text in info.value.message, info.value.message


def test_an_admin_adds_lists_reads_the_deliveries_of_and_removes_a_webhook(depot: Depot):
    admin = sdk(depot, depot.token("admin", name="alice"))
    added = admin.add_webhook("http://127.0.0.1:9000/hook", ["event:intervention", "robot.silent"], "slack")
    secret = added.pop("secret")
    assert secret.startswith("whsec_")
    assert added["id"].startswith("wh-") and added["created_by"] == "alice"
    assert (added["url"], added["on"], added["format"]) == (
        "http://127.0.0.1:9000/hook",
        ["event:intervention", "robot.silent"],
        "slack",
    )
    listed = admin.webhooks()
    assert listed == {"webhooks": [added]} and secret not in str(listed)
    assert admin.webhook_deliveries(added["id"]) == {"webhook": added["id"], "deliveries": [], "next_cursor": None}
    assert admin.remove_webhook(added["id"]) == {**added, "removed": True}
    assert admin.webhooks() == {"webhooks": []}
    refused(lambda: admin.remove_webhook(added["id"]), 404, f"no webhook {added['id']!r}")
    refused(lambda: admin.webhook_deliveries(added["id"]), 404)


@pytest.mark.parametrize("scopes", [("write",), ("read",), ("ingest",)])
def test_only_an_admin_may_touch_webhooks(depot: Depot, scopes: tuple[str, ...]):
    hook = sdk(depot, depot.token("admin")).add_webhook("http://127.0.0.1:9000/", ["run.sealed"])["id"]
    other = sdk(depot, depot.token(*scopes, robot="robot-7" if scopes == ("ingest",) else None))
    refused(lambda: other.add_webhook("http://127.0.0.1:9000/", ["run.sealed"]), 403)
    refused(other.webhooks, 403)
    refused(lambda: other.remove_webhook(hook), 403)
    refused(lambda: other.webhook_deliveries(hook), 403)
    nobody = sdk(depot, None)
    refused(nobody.webhooks, 401)
    refused(lambda: nobody.add_webhook("http://127.0.0.1:9000/", ["run.sealed"]), 401)
    assert [h["id"] for h in sdk(depot, depot.token("admin")).webhooks()["webhooks"]] == [hook]


@pytest.mark.parametrize(
    ("url", "says"),
    [
        ("https://hooks.invalid/x", ["hooks.invalid:443 is not in FLEET_WEBHOOK_HOSTS"]),
        ("http://169.254.169.254/latest/meta-data/", ["169.254.169.254", "link-local or metadata address"]),
        (f"http://127.0.0.1:{DEPOT_PORT}/v1/tokens", [f"127.0.0.1:{DEPOT_PORT}", "this depot's own port"]),
        ("file:///etc/passwd", ["http:// or https://"]),
        ("http://user:pw@127.0.0.1:9000/", ["no user or password"]),
    ],
)
def test_urls_the_depot_must_not_reach_are_refused_with_the_reason(depot: Depot, url: str, says: list[str]):
    admin = sdk(depot, depot.token("admin"))
    refused(lambda: admin.add_webhook(url, ["run.sealed"]), 422, *says)
    assert admin.webhooks() == {"webhooks": []}


def test_a_depot_with_no_webhook_host_says_which_setting_allows_one(tmp_path: Path, fresh_catalog_url: str):
    with open_depot(tmp_path, fresh_catalog_url) as bare:
        admin = sdk(bare, bare.token("admin"))
        refused(lambda: admin.add_webhook("https://hooks.example/", ["run.sealed"]), 422, "FLEET_WEBHOOK_HOSTS=")


def test_bad_requests_are_refused_with_the_reason(depot: Depot):
    admin = sdk(depot, depot.token("admin"))
    url = "http://127.0.0.1:9000/"
    refused(lambda: admin.add_webhook(url, []), 422, "at least one --on")
    refused(lambda: admin.add_webhook(url, ["event:"]), 422, "'event:' is nothing a webhook is told of")
    refused(lambda: admin.add_webhook(url, ["run.closed"]), 422, "run.sealed")
    refused(lambda: admin.add_webhook(url, ["event:*"], "xml"), 422, "use json or slack")
    refused(lambda: admin._request("POST", "/v1/webhooks", json={"on": ["run.sealed"]}), 422, "url")
    hook = admin.add_webhook(url, ["event:*"])["id"]
    refused(lambda: admin.webhook_deliveries(hook, limit=0), 422, "limit")
    refused(lambda: admin.webhook_deliveries(hook, cursor="garbage!"), 422, "cursor")
    refused(lambda: admin.remove_webhook("no such"), 422, "webhook_id")
    refused(lambda: admin.remove_webhook("wh-000000000000"), 404)
