"""A run a dataset snapshot uses is kept: retention's plan keeps it past its policy and says why, a
person's delete is refused naming the snapshots, and an admin's forced delete leaves the
snapshot's episode answering `missing`."""

from __future__ import annotations

from services.policies import Policies, Policy
from services.retention import service as retention
from services.retention.service import Retention
from tests.services.auth.conftest import Depot, bearer
from tests.services.corpus.conftest import refused, sdk
from tests.services.datasets.conftest import upload, writer


def _expire_everything(depot: Depot) -> Retention:
    """Retention with a policy that keeps nothing: every sealed run is due for deletion now."""
    ctx: Retention = depot.app.state.retention
    ctx.policies = Policies(Policy("brief", 0, 0))
    return ctx


def test_the_plan_keeps_a_used_run_and_says_why(depot: Depot):
    upload(depot, "run-used", seal=True)
    upload(depot, "run-free", seal=True)
    upload(depot, "run-pinned", seal=True)
    sdk(depot, depot.token("write")).pin("run-pinned")
    alice = writer(depot)
    alice.create_dataset("picks", robot=["robot-7"], tag=[])  # all three
    depot.client.post("/v1/runs/run-used/tags", json={"tags": ["keep"]}, headers=bearer(depot.token("write")))
    alice.create_dataset("picks", tag=["keep"])  # picks@2: run-used only
    alice.create_dataset("other", tag=["keep"])
    ctx = _expire_everything(depot)

    assert [(a.run_id, a.action) for a in retention.plan(ctx, ["delete"])] == []  # all three are in picks@1
    plan = sdk(depot, depot.token("read")).retention_plan(["delete"])
    kept = {k["run"]: (k["action"], k["reason"]) for k in plan["kept"]}
    assert kept["run-used"] == ("keep", "used by datasets other@1, picks@1, picks@2")
    assert kept["run-free"] == ("keep", "used by dataset picks@1")
    assert kept["run-pinned"][1].startswith("pinned by ") and kept["run-pinned"][1].endswith("used by dataset picks@1")


def test_an_unused_run_is_deleted_by_the_plan_and_a_used_one_is_not(depot: Depot):
    upload(depot, "run-used", seal=True)
    upload(depot, "run-free", seal=True)
    writer(depot).tag("run-used", ["keep"])
    writer(depot).create_dataset("picks", tag=["keep"])
    ctx = _expire_everything(depot)
    due = retention.plan(ctx, ["delete"])
    assert [(a.run_id, a.action) for a in due] == [("run-free", "delete")]
    assert all(o.ok for o in retention.run_plan(ctx, due))
    reader = sdk(depot, depot.token("read"))
    assert reader.run("run-free")["tier"] == "deleted" and reader.run("run-used")["tier"] == "warm"


def test_a_snapshot_made_after_the_plan_still_keeps_its_run(depot: Depot):
    upload(depot, "run-a", seal=True)
    ctx = _expire_everything(depot)
    due = retention.plan(ctx, ["delete"])
    writer(depot).create_dataset("late")
    (outcome,) = retention.run_plan(ctx, due)
    assert outcome.detail == "kept: used by dataset late@1"
    assert sdk(depot, depot.token("read")).run("run-a")["tier"] == "warm"


def test_deleting_a_used_run_is_refused_naming_the_snapshot_unless_forced(depot: Depot):
    upload(depot, "run-a", seal=True)
    upload(depot, "run-b", seal=True)
    writer(depot).create_dataset("picks")
    admin = sdk(depot, depot.token("admin"))
    refused(lambda: admin.delete_run("run-a"), 409, "used by dataset picks@1", "force=true")
    assert writer(depot).dataset_version("picks", 1)["episodes_page"][0]["missing"] is False

    assert admin.delete_run("run-a", force=True)["run"] == "run-a"
    first, second = writer(depot).dataset_version("picks", 1)["episodes_page"]
    assert (first["run_id"], first["missing"]) == ("run-a", True)
    assert first["missing_why"].startswith("run deleted on ") and first["missing_why"].endswith("by admin")
    assert (second["run_id"], second["missing"], second["missing_why"]) == ("run-b", False, None)
    again = writer(depot).create_dataset("picks")  # the deleted run is no longer selected
    assert [e["run_id"] for e in writer(depot).dataset_version("picks", 2)["episodes_page"]] == ["run-b"]
    assert again["runs"] == 1
