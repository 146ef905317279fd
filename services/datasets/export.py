"""Episodes exported as a LeRobot v3.0 dataset: each episode's chunks read from its recording (a run
of the depot, hot or sealed, or an episode downloaded by the command line), sampled onto a fixed
grid of `fps` frames per second by latest-at (as Rerun's own exporter does), checked, and written
by the LeRobot writer episode by episode, so an export killed midway resumes after its last
written episode.

The grid of an episode runs over its window (a whole-run episode: from the first to the last row
of its exported entities), on the snapshot's timeline, which must count time (timestamp or
duration); frames before every exported entity has a row are left out. The observation vector is
the observation entities' scalars in entity-path order, each entity's instances in their order; the
action vector likewise; each camera a video feature. Memory is bounded whatever an episode's
length: the grid is sampled in slices (`grid.py`), vectors are kept (floats per frame), camera
frames are decoded one at a time as the video is written.

An episode that cannot be exported (an entity missing, no frame) is skipped and reported; the
LeRobot episodes are numbered in order over those written.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.errors import BadParameterError, ConflictError
from services.datasets import frames
from services.datasets import quality as checks
from services.datasets.lerobot import layout
from services.datasets.lerobot.layout import Features
from services.datasets.lerobot.writer import PROGRESS_DIR, Episode, LeRobotWriter
from services.datasets.quality import EpisodeQuality, Flag, Limits
from services.rrd.chunk_index import IndexRow
from services.runs.indexed import IndexedRecording

CODECS = ("h264", "av1")
SPEC_FILE = "spec.json"  # in the writer's progress folder: a resumed export must ask the same
FEATURES_FILE = "features.json"  # the first exported episode's features, which every episode keeps


@dataclass(frozen=True)
class ExportSpec:
    """What goes where: entity patterns for the state and the action, cameras as (entity, feature
    key), the task (text, or a recording property of each run: `task_property`), the rate and the
    video codec."""

    observation: tuple[str, ...]
    action: tuple[str, ...]
    cameras: tuple[tuple[str, str], ...] = ()
    task: str = ""
    fps: int = 10
    codec: str = "h264"
    task_property: str | None = None

    def check(self) -> None:
        if not 1 <= self.fps <= 1000:
            raise BadParameterError("fps", f"{self.fps}: a whole number of frames per second, 1 to 1000")
        if not self.observation and not self.action and not self.cameras:
            raise BadParameterError("observation", "name what to export: --observation, --action or --camera")
        if self.codec not in CODECS:
            raise BadParameterError("video_codec", f"{self.codec!r}: one of {', '.join(CODECS)}")
        keys = [key for _, key in self.cameras]
        for entity, key in self.cameras:
            if not key.startswith("observation.images.") or "/" in key or len(key) <= len("observation.images."):
                raise BadParameterError("camera", f"{entity}={key}: the feature is observation.images.NAME")
        if len(set(keys)) != len(keys):
            raise BadParameterError("camera", "two cameras with one feature key: give each its own NAME")

    def as_json(self) -> dict[str, Any]:
        return {
            "observation": list(self.observation),
            "action": list(self.action),
            "cameras": [[entity, key] for entity, key in self.cameras],
            "task": self.task,
            "task_property": self.task_property,
            "fps": self.fps,
            "codec": self.codec,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ExportSpec:
        """What `as_json` wrote (keys it does not write are left alone)."""
        return cls(
            tuple(data["observation"]),
            tuple(data["action"]),
            tuple((entity, key) for entity, key in data["cameras"]),
            data["task"],
            int(data["fps"]),
            data["codec"],
            data["task_property"],
        )


@dataclass(frozen=True)
class EpisodeInfo:
    """A snapshot's episode as an export needs it."""

    episode: int
    run_id: str
    timeline: str
    range_start: int | None
    range_end: int | None


@dataclass
class OpenedEpisode:
    """An episode's recording and the index rows of the chunks it reads; whether its run is hot
    (still growing), its recording properties (for a task taken from one)."""

    recording: IndexedRecording
    rows: list[IndexRow]
    hot: bool = False
    properties: Mapping[str, Any] = field(default_factory=dict)


OpenEpisode = Callable[[EpisodeInfo], AbstractContextManager[OpenedEpisode]]


@dataclass
class EpisodeReport:
    episode: int
    run_id: str
    exported_as: int | None  # the LeRobot episode index; None: skipped
    frames: int
    flags: list[Flag]

    def as_json(self) -> dict[str, Any]:
        return {
            "episode": self.episode,
            "run": self.run_id,
            "exported_as": self.exported_as,
            "frames": self.frames,
            "flags": [f.as_json() for f in self.flags],
        }


@dataclass
class Progress:
    episodes: int
    done: int = 0
    frames: int = 0
    skipped: int = 0
    flagged: int = 0
    last: EpisodeReport | None = None  # the episode just done


@dataclass
class ExportResult:
    info: dict[str, Any] | None  # info.json's contents (None: a check, nothing written)
    reports: list[EpisodeReport]


class QualityError(ConflictError):
    """A strict export refused: episodes with flags."""


class Unreadable(ConflictError):
    """An episode whose run cannot be read now (deleted, cold, hot on another node): flagged, skipped."""


def export_episodes(
    episodes: Iterable[EpisodeInfo],
    total: int,
    open_episode: OpenEpisode,
    spec: ExportSpec,
    root: Path | None,
    *,
    limits: Limits | None = None,
    progress: Callable[[Progress], None] | None = None,
) -> ExportResult:
    """Write the episodes under `root` (resuming an export there), or with `root` None only check
    them; the LeRobot info and a report per episode."""
    spec.check()
    limits = limits or Limits()
    run = _Export(spec, root, limits, open_episode)
    state = Progress(total)
    for info in episodes:
        report = run.episode(info)
        run.reports.append(report)
        state.done += 1
        state.frames += report.frames if report.exported_as is not None or root is None else 0
        state.skipped += report.exported_as is None and root is not None
        state.flagged += bool(report.flags)
        state.last = report
        if progress is not None:
            progress(state)
    return ExportResult(run.finish() if root is not None else None, run.reports)


def refuse_flagged(reports: Sequence[EpisodeReport]) -> None:
    """A strict export's refusal, naming the flagged episodes."""
    flagged = [r for r in reports if r.flags]
    if flagged:
        said = "; ".join(
            f"episode {r.episode} ({r.run_id}): "
            + ", ".join(f.check + (f" {f.entity}" if f.entity else "") for f in r.flags)
            for r in flagged[:10]
        )
        more = f" and {len(flagged) - 10} more" if len(flagged) > 10 else ""
        raise QualityError(
            f"{len(flagged)} episode(s) have quality flags: {said}{more}. "
            "Export without --strict to write them anyway (flagged episodes are reported), "
            "or make a snapshot without them"
        )


class _Export:
    def __init__(self, spec: ExportSpec, root: Path | None, limits: Limits, open_episode: OpenEpisode) -> None:
        self.spec, self.root, self.limits, self.open_episode = spec, root, limits, open_episode
        self.writer: LeRobotWriter | None = None
        self.done: dict[int, dict[str, Any]] = {}  # records by snapshot episode (a resumed export)
        self.records: list[dict[str, Any]] = []
        self.reports: list[EpisodeReport] = []
        if root is not None:
            self._resume(root)

    def _resume(self, root: Path) -> None:
        """What an export killed in `root` had written: the same options asked again, or a refusal."""
        progress = root / PROGRESS_DIR
        progress.mkdir(parents=True, exist_ok=True)
        asked = json.dumps(self.spec.as_json(), sort_keys=True)
        saved = progress / SPEC_FILE
        if saved.exists() and saved.read_text() != asked:
            raise ConflictError(
                f"{root} holds an export asked with other options ({saved.read_text()}): "
                "export into an empty folder, or ask the same again to resume it"
            )
        saved.write_text(asked)
        found = progress / FEATURES_FILE
        if found.exists():
            self._open_writer(Features.from_json(json.loads(found.read_text())))

    def _open_writer(self, features: Features) -> None:
        assert self.root is not None
        layout.write_json(self.root / PROGRESS_DIR / FEATURES_FILE, features.as_json())
        self.writer = LeRobotWriter(self.root, fps=self.spec.fps, features=features, codec=self.spec.codec)
        self.done = {int(r["source"]["episode"]): r for r in self.writer.written().values()}

    def episode(self, info: EpisodeInfo) -> EpisodeReport:
        held = self.done.get(info.episode)
        if held is not None:  # written before a kill: its record stands
            self.records.append(held)
            source = held["source"]
            flags = [Flag(f["check"], f["entity"], f["detail"]) for f in source["flags"]]
            return EpisodeReport(info.episode, info.run_id, int(held["episode_index"]), int(held["length"]), flags)
        try:
            with self.open_episode(info) as opened:
                return self._read(info, opened)
        except Unreadable as exc:
            return EpisodeReport(info.episode, info.run_id, None, 0, [Flag(checks.MISSING_RUN, None, str(exc))])

    def _read(self, info: EpisodeInfo, opened: OpenedEpisode) -> EpisodeReport:
        spec = self.spec
        quality = EpisodeQuality(self.limits, frozenset(entity for entity, _ in spec.cameras))
        if opened.hot:
            quality.add(Flag(checks.HOT, None, "its run is still hot: read as it stands now"))
        episode = frames.plan(
            info.timeline, (info.range_start, info.range_end), opened.recording, opened.rows, spec, quality
        )
        if episode is None:
            return EpisodeReport(info.episode, info.run_id, None, 0, quality.flags())
        if self.writer is None and self.root is not None:
            self._open_writer(frames.features(episode, spec, spec.codec))
        first = self.writer.features if self.writer is not None else None
        vectors = frames.vectors(episode, first, quality)
        length = len(episode.grid)
        if length < self.limits.min_frames:
            quality.add(Flag(checks.SHORT, None, f"{length} frame(s), fewer than {self.limits.min_frames}"))
        if vectors is None or self.writer is None:  # skipped, or a check: the cameras' rows read for their flags
            if vectors is not None:
                for entity, _ in spec.cameras:
                    for _ in frames.camera_slices(episode, entity, quality):
                        pass
            return EpisodeReport(info.episode, info.run_id, None, length if vectors is not None else 0, quality.flags())
        cameras = {
            camera.key: frames.frames(episode, entity, camera, quality)
            for (entity, _), camera in zip(spec.cameras, self.writer.features.cameras, strict=True)
        }
        said: list[Flag] = []

        def describe() -> Mapping[str, Any]:  # after the videos are written: their frames' flags are known
            said.extend(quality.flags())
            return {"episode": info.episode, "run": info.run_id, "flags": [f.as_json() for f in said]}

        index = len(self.records)
        first_index = sum(int(r["length"]) for r in self.records)
        record = self.writer.write(Episode(index, _task(spec, opened), length, vectors, cameras, describe), first_index)
        self.records.append(record)
        return EpisodeReport(info.episode, info.run_id, index, length, said)

    def finish(self) -> dict[str, Any]:
        if self.writer is None:
            raise ConflictError(
                "no episode could be exported: "
                + "; ".join(f"episode {r.episode}: " + ", ".join(f.detail for f in r.flags) for r in self.reports[:5])
                if self.reports
                else "the version has no episodes"
            )
        return self.writer.finish(self.records)


def _task(spec: ExportSpec, opened: OpenedEpisode) -> str:
    """The episode's task: its run's recording property named (`NAME.FIELD`), else the text given."""
    if spec.task_property is not None:
        name, _, field_name = spec.task_property.partition(".")
        held = opened.properties.get(name)
        value = held.get(field_name) if isinstance(held, dict) else None
        if isinstance(value, list) and len(value) == 1:
            value = value[0]
        if value is not None:
            return value if isinstance(value, str) else json.dumps(value, sort_keys=True)
    return spec.task
