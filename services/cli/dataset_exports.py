"""`fleet datasets export|exports|export-cancel`: a snapshot version exported as a LeRobot dataset.

`--to DIR` (a folder of this machine) exports here: each episode's chunks downloaded
(`GET /v1/datasets/NAME/N/episodes/K/recording.rrd`, exactly the snapshot's), sampled and written
episode by episode; a killed export resumes when the same command is run again. `--to URL`
(file:///PATH or s3://BUCKET/PREFIX) asks the depot to export into a place it may write: a job
whose progress is followed until it ends (`--detach` to leave it).
"""

from __future__ import annotations

import json
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn
from rich.table import Table

from services.cli.client import api_option, client
from services.cli.output import stdout_console

if TYPE_CHECKING:  # the export's modules (Arrow, PyAV, the catalog) load when a command needs them
    from services.datasets.export import EpisodeInfo, EpisodeReport, ExportResult, ExportSpec, OpenedEpisode
    from services.datasets.export import Progress as ExportProgress
    from services.datasets.quality import Limits

POLL_S = 1.0
PAGE = 1000


def export_options(command: Any) -> Any:
    for option in reversed(
        [
            click.option("--format", "fmt", default="lerobot", show_default=True, type=click.Choice(["lerobot"])),
            click.option("--to", "target", required=True, help="a folder here, or file:///PATH or s3://BUCKET/PREFIX"),
            click.option(
                "--observation", multiple=True, help="entities of observation.state: /a/b or /a/** (repeatable)"
            ),
            click.option("--action", multiple=True, help="entities of action (repeatable)"),
            click.option("--camera", multiple=True, help="ENTITY=observation.images.NAME: an Image entity's video"),
            click.option("--task", default="", help="the episodes' task text"),
            click.option("--task-property", help="a recording property NAME.FIELD as each run's task"),
            click.option("--fps", type=int, help="frames per second (default: the snapshot's, else 10)"),
            click.option("--video-codec", default="h264", show_default=True, type=click.Choice(["h264", "av1"])),
            click.option("--strict", is_flag=True, help="refuse the export if any episode has a quality flag"),
            click.option(
                "--frozen-s", type=float, default=2.0, show_default=True, help="a camera unchanged this long is frozen"
            ),
            click.option(
                "--min-frames", type=int, default=1, show_default=True, help="an episode of fewer frames is short"
            ),
        ]
    ):
        command = option(command)
    return command


def cameras_of(items: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    out = []
    for item in items:
        entity, sep, key = item.partition("=")
        if not sep or not entity or not key:
            raise click.BadParameter(f"{item!r} is not ENTITY=observation.images.NAME", param_hint="--camera")
        out.append((entity, key))
    return tuple(out)


@click.command("export")
@api_option
@click.argument("ref")
@export_options
@click.option("--detach", is_flag=True, help="with --to URL: queue the depot's job and return")
@click.option("--json", "as_json", is_flag=True, help="print the report (or the job) as JSON")
def export(api_url: str, ref: str, target: str, fmt: str, detach: bool, as_json: bool, **options: Any) -> None:
    """Export version NAME@N as a LeRobot v3.0 dataset: `--observation /joints/** --action /cmd/**
    --camera /camera/front=observation.images.front --task "pick the box" --to DIR`."""
    from services.datasets.export import ExportSpec
    from services.datasets.exports import default_fps, parse_version
    from services.datasets.quality import Limits

    name, number = parse_version(ref)
    cameras = cameras_of(options["camera"])
    limits = Limits(options["frozen_s"], options["min_frames"])
    with client(api_url) as fleet:
        if "://" in target:
            body = {
                "format": fmt,
                "observation": list(options["observation"]),
                "action": list(options["action"]),
                "cameras": dict(cameras),
                "task": options["task"],
                "task_property": options["task_property"],
                "fps": options["fps"],
                "video_codec": options["video_codec"],
                "strict": options["strict"],
                "frozen_s": limits.frozen_s,
                "min_frames": limits.min_frames,
            }
            job = fleet.export_dataset(ref, target, **body)
            if not detach:
                job = _follow_job(fleet, job)
            _print_job(job, as_json)
            if job["state"] == "failed":
                raise SystemExit(1)
            return
        fps = options["fps"] or default_fps(fleet.dataset_version(name, number, limit=1)["selection"])
        spec = ExportSpec(
            tuple(options["observation"]),
            tuple(options["action"]),
            cameras,
            options["task"],
            fps,
            options["video_codec"],
            options["task_property"],
        )
        result = export_here(fleet, name, number, spec, Path(target), limits, options["strict"])
    _print_reports(result, as_json)


def export_here(
    fleet: Any, name: str, number: int, spec: ExportSpec, root: Path, limits: Limits, strict: bool
) -> ExportResult:
    """The export written under `root` by this process (resumed if it was killed there)."""
    from services.datasets.export import export_episodes, refuse_flagged

    spec.check()
    total = int(fleet.dataset_version(name, number, limit=1)["episodes"])
    opener = _opener(fleet, name, number, spec)
    if strict:
        checked = _with_progress(f"checking {name}@{number}", total, lambda p: export_episodes(
            _episodes(fleet, name, number), total, opener, spec, None, limits=limits, progress=p
        ))  # fmt: skip
        refuse_flagged(checked.reports)
    root.mkdir(parents=True, exist_ok=True)
    return _with_progress(f"exporting {name}@{number}", total, lambda p: export_episodes(
        _episodes(fleet, name, number), total, opener, spec, root, limits=limits, progress=p
    ))  # fmt: skip


def _with_progress(title: str, total: int, body: Any) -> ExportResult:
    err = Console(stderr=True)
    columns = ("{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=err, transient=True) as bar:
        task = bar.add_task(title, total=total)

        def seen(progress: ExportProgress) -> None:
            bar.update(task, completed=progress.done, description=f"{title}: {progress.frames:,} frames")

        result: ExportResult = body(seen)
        return result


def _episodes(fleet: Any, name: str, number: int) -> Iterator[EpisodeInfo]:
    from services.datasets.export import EpisodeInfo

    cursor: str | None = None
    while True:
        page = fleet.dataset_version(name, number, limit=PAGE, cursor=cursor)
        for e in page["episodes_page"]:
            yield EpisodeInfo(int(e["index"]), e["run_id"], e["timeline"], e["start"], e["end"])
        cursor = page["next_cursor"]
        if not cursor:
            return


def _opener(fleet: Any, name: str, number: int, spec: ExportSpec) -> Any:
    @contextmanager
    def open_episode(info: EpisodeInfo) -> Iterator[OpenedEpisode]:
        from sdk_client.rest import ServiceError
        from services.datasets.export import OpenedEpisode, Unreadable
        from services.datasets.local import open_rrd_file

        with tempfile.TemporaryDirectory(prefix="fleet-episode-") as folder:
            path = Path(folder) / "episode.rrd"
            try:
                fleet.download_episode(name, number, info.episode, path)
                run = fleet.run(info.run_id)
            except ServiceError as exc:
                if exc.status in (404, 409, 410):
                    raise Unreadable(str(exc)) from exc
                raise
            recording = open_rrd_file(path)
            try:
                yield OpenedEpisode(recording, list(recording.index()), run["tier"] == "hot", run["properties"])
            finally:
                recording.close()

    return open_episode


def _print_reports(result: ExportResult, as_json: bool) -> None:
    reports = result.reports
    if as_json:
        click.echo(json.dumps({"info": result.info, "episodes": [r.as_json() for r in reports]}, indent=2))
        return
    written = [r for r in reports if r.exported_as is not None]
    frames = sum(r.frames for r in written)
    click.echo(f"{len(written)} of {len(reports)} episodes exported, {frames:,} frames")
    _flag_table([r for r in reports if r.flags or r.exported_as is None])


def _flag_table(reports: list[EpisodeReport] | list[dict[str, Any]]) -> None:
    if not reports:
        return
    from services.datasets.export import EpisodeReport

    table = Table("episode", "run", "exported", "check", "entity", "detail", box=None, padding=(0, 2))
    for r in reports:
        found = r.as_json() if isinstance(r, EpisodeReport) else r
        for flag in found["flags"] or [{"check": "-", "entity": None, "detail": ""}]:
            exported = "no" if found["exported_as"] is None else f"as {found['exported_as']}"
            table.add_row(
                str(found["episode"]), found["run"], exported, flag["check"], flag["entity"] or "", flag["detail"]
            )
    stdout_console().print(table)


def _follow_job(fleet: Any, job: dict[str, Any]) -> dict[str, Any]:
    err = Console(stderr=True)
    columns = ("{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=err, transient=True) as bar:
        task = bar.add_task(f"export {job['id']} ({job['state']})", total=job["episodes"])
        while job["state"] in ("queued", "running"):
            time.sleep(POLL_S)  # the job runs in the depot: its progress is polled
            job = fleet.export(job["id"])
            bar.update(
                task,
                completed=job["done"],
                description=f"export {job['id']} ({job['state']}): {job['frames']:,} frames",
            )
    return job


def _print_job(job: dict[str, Any], as_json: bool) -> None:
    if as_json:
        click.echo(json.dumps(job, indent=2))
        return
    click.echo(
        f"{job['id']} {job['dataset']} -> {job['to']}: {job['state']}, {job['done']}/{job['episodes']} episodes, "
        f"{job['frames']:,} frames, {job['bytes'] / 1e6:,.1f} MB" + (f"; {job['error']}" if job["error"] else "")
    )
    _flag_table(job["report"])


@click.command("exports")
@api_option
@click.argument("dataset", required=False)
@click.option("--limit", type=int, default=50, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="print the service's JSON answer")
def exports(api_url: str, dataset: str | None, limit: int, as_json: bool) -> None:
    """The depot's export jobs, newest first (of DATASET: NAME or NAME@N)."""
    with client(api_url) as fleet:
        found = fleet.exports(dataset, limit)
    if as_json:
        click.echo(json.dumps(found, indent=2))
        return
    table = Table("id", "dataset", "to", "state", "episodes", "frames", "flagged", "by", "at", box=None, padding=(0, 2))
    for job in found:
        table.add_row(
            job["id"],
            job["dataset"],
            job["to"],
            job["state"] + (f": {job['error']}" if job["error"] else ""),
            f"{job['done']}/{job['episodes']}",
            f"{job['frames']:,}",
            str(job["flagged"]),
            job["created_by"],
            job["created_at"],
        )
    stdout_console().print(table)


@click.command("export-cancel")
@api_option
@click.argument("job_id")
def export_cancel(api_url: str, job_id: str) -> None:
    """Cancel a queued or running export job of the depot."""
    with client(api_url) as fleet:
        job = fleet.cancel_export(job_id)
    click.echo(f"{job['id']}: {job['state']}")
