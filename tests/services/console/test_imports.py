"""Imports in the console (auth on): every upload, RRD or MCAP, newest first with its state and, when
it failed, why, as `GET /v1/imports` lists it; filtered by state and kind and paged by `before`; one
import with every field; a failed MCAP import's Retry button (write scope, a CSRF-checked form post
running the same retry as `POST /v1/imports/ID/retry`) and its original for an admin."""

from __future__ import annotations

import html
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from services.console import imports as console_imports
from services.console.app import install
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.console.test_sessions import CSRF, log_in
from tests.services.datasets.conftest import ROBOT, upload
from tests.services.imports.mcaps import json_mcap, truncated

ROW = re.compile(r'<tr data-import="([^"]+)" data-kind="(\w+)" data-state="(\w+)">(.*?)</tr>', re.S)
CELL = re.compile(r"<td[^>]*>(.*?)</td>", re.S)
RUN = "run-imported"


@dataclass
class Imports:
    depot: Depot
    rrd: str  # a filed RRD upload's import (robot ROBOT, run RUN)
    mcap: str  # a failed MCAP upload's import (a truncated file), its original in quarantine
    original: bytes  # that MCAP upload's bytes

    def rest(self, path: str, **params: Any) -> dict[str, Any]:
        answer = self.depot.client.get(path, params=params, headers=bearer(self.depot.token("read")))
        assert answer.status_code == 200, answer.text
        found: dict[str, Any] = answer.json()
        return found


@pytest.fixture
def imports(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Imports]:
    with open_depot(tmp_path, fresh_catalog_url) as depot:
        install(depot.app)
        upload(depot, RUN)
        listed = depot.client.get("/v1/imports", headers=bearer(depot.token("read"))).json()["imports"]
        (rrd,) = [i["id"] for i in listed if i["kind"] == "rrd"]
        bad = truncated(json_mcap(tmp_path / "good.mcap", 3000), tmp_path / "drive.mcap")
        answer = depot.client.post(
            "/v1/uploads", content=bad.read_bytes(), params={"name": "drive.mcap"}, headers=bearer(depot.token("write"))
        )
        assert answer.status_code == 400 and answer.json()["code"] == "INVALID_MCAP", answer.text
        yield Imports(depot, rrd, answer.json()["import"]["id"], bad.read_bytes())


def signed_in(depot: Depot, scope: str) -> TestClient:
    return log_in(TestClient(depot.app), depot.token(scope, name=f"{scope}-person"))


def page(browser: TestClient, path: str, status: int = 200) -> str:
    answer = browser.get(path, follow_redirects=False)
    assert answer.status_code == status, answer.text[:2000]
    assert answer.headers["content-type"].startswith("text/html")
    text: str = answer.text
    return text


def rows(text: str) -> list[dict[str, Any]]:
    """The imports table as the page shows it: each row's id, kind, state and cell texts."""
    return [
        {
            "id": import_id,
            "kind": kind,
            "state": state,
            "cells": [html.unescape(re.sub(r"<[^>]+>", "", c)).strip() for c in CELL.findall(body)],
            "body": body,
        }
        for import_id, kind, state, body in ROW.findall(text)
    ]


def csrf_of(text: str) -> str:
    found = CSRF.search(text)
    assert found
    return found.group(1)


# --- the list -----------------------------------------------------------------------------------------


def test_the_list_shows_a_filed_rrd_and_a_failed_mcap_upload_with_its_reason(imports: Imports) -> None:
    browser = signed_in(imports.depot, "read")
    text = page(browser, "/console/imports")
    assert '<a href="/console/imports" aria-current="page">Imports</a>' in text  # the header's menu
    assert '<a href="/console/imports"' in page(browser, "/console/runs")  # on every page

    listed = imports.rest("/v1/imports")["imports"]
    shown = rows(text)
    assert [r["id"] for r in shown] == [i["id"] for i in listed] == [imports.mcap, imports.rrd]  # newest first
    failed, filed = shown
    answer = {i["id"]: i for i in listed}

    assert (failed["kind"], failed["state"]) == ("mcap", "failed")
    reason = answer[imports.mcap]["reason"]
    assert reason and "truncated" in reason
    assert failed["cells"][0] == imports.mcap and failed["cells"][3] == "drive.mcap"
    assert failed["cells"][-1] == reason  # why it failed, as the API says
    assert f'href="/console/imports/{imports.mcap}"' in failed["body"]
    assert f'title="{len(imports.original):,} bytes"' in failed["body"]

    assert (filed["kind"], filed["state"]) == ("rrd", "filed")
    assert filed["cells"][5] == ROBOT and filed["cells"][6] == RUN
    assert f'<a class="import-run" href="/console/runs/{RUN}">{RUN}</a>' in filed["body"]  # the run's page
    assert filed["cells"][7] == f"{answer[imports.rrd]['chunks_new']:,}" != "0"
    assert filed["cells"][8].endswith(" UTC") and filed["cells"][-1] == ""


def test_the_filters_select_by_state_and_kind_and_a_bad_one_is_said(imports: Imports) -> None:
    browser = signed_in(imports.depot, "read")
    assert [r["id"] for r in rows(page(browser, "/console/imports?state=failed"))] == [imports.mcap]
    assert [r["id"] for r in rows(page(browser, "/console/imports?state=filed"))] == [imports.rrd]
    assert [r["id"] for r in rows(page(browser, "/console/imports?kind=rrd"))] == [imports.rrd]
    assert [r["id"] for r in rows(page(browser, "/console/imports?kind=mcap&state=failed"))] == [imports.mcap]
    assert [r["id"] for r in rows(page(browser, f"/console/imports?robot={ROBOT}"))] == [imports.rrd]
    none = page(browser, "/console/imports?kind=mcap&state=filed")
    assert rows(none) == [] and 'id="no-imports"' in none and "clear them" in none
    selected = page(browser, "/console/imports?state=failed")
    assert '<option value="failed" selected>failed</option>' in selected

    bad = page(browser, "/console/imports?state=lost", status=422)
    assert 'id="problem"' in bad and "receiving, converting, filed, failed" in html.unescape(bad)
    assert rows(bad) == []


def test_the_list_pages_by_before_as_the_rest_route_does(imports: Imports, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(console_imports, "PAGE", 1)
    browser = signed_in(imports.depot, "read")
    first = page(browser, "/console/imports")
    assert [r["id"] for r in rows(first)] == [imports.mcap]
    assert imports.rest("/v1/imports", limit=1)["next_before"] == imports.mcap
    found = re.search(r'<a href="([^"]+)" id="next-page"', first)
    assert found and html.unescape(found[1]) == f"/console/imports?before={imports.mcap}"
    second = page(browser, html.unescape(found[1]))
    assert [r["id"] for r in rows(second)] == [imports.rrd] and 'id="first-page"' in second


# --- one import ---------------------------------------------------------------------------------------


def test_an_imports_page_shows_its_fields_and_why_it_failed(imports: Imports) -> None:
    browser = signed_in(imports.depot, "read")
    text = page(browser, f"/console/imports/{imports.mcap}")
    answer = imports.rest(f"/v1/imports/{imports.mcap}")
    assert '<a href="/console/imports" aria-current="page">Imports</a>' in text
    assert f'<code id="import-id">{imports.mcap}</code>' in text and 'data-state="failed"' in text
    reason = re.search(r'<dd id="reason" class="reason">(.*?)</dd>', text, re.S)
    assert reason and html.unescape(reason[1]) == answer["reason"]
    assert '<dd id="name">drive.mcap</dd>' in text
    assert '<dd id="quarantined">yes, until ' in text and answer["quarantined"] is True
    assert f'<dd id="created-by">{answer["created_by"]}</dd>' in text

    rrd = page(browser, f"/console/imports/{imports.rrd}")
    assert f'<a class="import-run" href="/console/runs/{RUN}">{RUN}</a>' in rrd
    assert 'id="reason"' not in rrd and 'id="actions"' not in rrd

    missing = page(browser, "/console/imports/imp-000000000000", status=404)
    assert "NOT_FOUND" in missing and "fleet imports ls" in missing


def test_the_retry_button_is_shown_to_a_writer_and_not_to_a_reader(imports: Imports) -> None:
    path = f"/console/imports/{imports.mcap}"
    reader = page(signed_in(imports.depot, "read"), path)
    assert 'id="retry-form"' not in reader and 'id="retry-needs-write"' in reader
    assert 'id="download-original"' not in reader

    writer = page(signed_in(imports.depot, "write"), path)
    form = re.search(r'<form method="post" action="([^"]+)" class="inline" id="retry-form">(.*?)</form>', writer, re.S)
    assert form and form[1] == f"{path}/retry" and 'name="csrf"' in form[2]
    assert 'id="download-original"' not in writer  # an admin's

    admin = page(signed_in(imports.depot, "admin"), path)
    assert f'<a id="download-original" href="{path}/original" download>' in admin

    # An RRD import is never retried from the console (send the file again).
    assert 'id="retry-form"' not in page(signed_in(imports.depot, "write"), f"/console/imports/{imports.rrd}")


def test_a_retry_without_the_csrf_value_or_the_write_scope_is_refused(imports: Imports) -> None:
    path = f"/console/imports/{imports.mcap}"
    before = imports.rest(f"/v1/imports/{imports.mcap}")
    writer = signed_in(imports.depot, "write")
    page(writer, path)
    for data in ({}, {"csrf": "forged"}):
        refused = writer.post(f"{path}/retry", data=data, follow_redirects=False)
        assert refused.status_code == 403 and "CSRF" in html.unescape(refused.text)
    reader = signed_in(imports.depot, "read")
    csrf = csrf_of(page(reader, path))  # a valid value for the reader's session: the scope refuses it
    refused = reader.post(f"{path}/retry", data={"csrf": csrf}, follow_redirects=False)
    assert refused.status_code == 403 and 'id="problem"' in refused.text and "&#39;write&#39;" in refused.text
    assert imports.rest(f"/v1/imports/{imports.mcap}") == before  # nothing was retried


def test_a_writers_retry_runs_the_imports_retry_and_shows_how_it_went(imports: Imports) -> None:
    path = f"/console/imports/{imports.mcap}"
    writer = signed_in(imports.depot, "write")
    csrf = csrf_of(page(writer, path))
    answer = writer.post(f"{path}/retry", data={"csrf": csrf}, follow_redirects=False)
    assert answer.status_code == 303 and answer.headers["location"] == f"{path}?done=retry-failed"
    text = page(writer, answer.headers["location"])
    assert 'id="notice"' in text and "failed again" in text  # the same truncated file
    after = imports.rest(f"/v1/imports/{imports.mcap}")
    assert after["state"] == "failed" and after["quarantined"] and "truncated" in after["reason"]
    reason = re.search(r'<dd id="reason" class="reason">(.*?)</dd>', text, re.S)
    assert reason and html.unescape(reason[1]) == after["reason"]

    rrd = f"/console/imports/{imports.rrd}"
    refused = writer.post(f"{rrd}/retry", data={"csrf": csrf}, follow_redirects=False)  # not retryable: 409 shown
    assert refused.status_code == 409 and 'id="problem"' in refused.text and "send the file again" in refused.text


def test_an_admin_downloads_the_quarantined_original(imports: Imports) -> None:
    path = f"/console/imports/{imports.mcap}/original"
    answer = signed_in(imports.depot, "admin").get(path)
    assert answer.status_code == 200 and answer.content == imports.original
    assert answer.headers["content-disposition"] == 'attachment; filename="drive.mcap"'
    assert page(signed_in(imports.depot, "write"), path, status=403)
    missing = page(signed_in(imports.depot, "admin"), f"/console/imports/{imports.rrd}/original", status=404)
    assert "no original in quarantine" in missing
