"""Synthetic episodes for the LeRobot writer's tests: values that say which frame they are."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from services.datasets.lerobot.layout import Camera, Features, Vector
from services.datasets.lerobot.writer import Episode

FPS = 10
WIDTH, HEIGHT = 64, 48
JOINTS = tuple(f"joint_{i}" for i in range(6))
FEATURES = Features(
    vectors=[Vector("observation.state", JOINTS), Vector("action", JOINTS)],
    cameras=[Camera("observation.images.front", HEIGHT, WIDTH)],
)


def state(episode: int, length: int) -> np.ndarray:
    frame = np.arange(length, dtype=np.float32)[:, None]
    return (episode * 100 + frame + np.arange(6, dtype=np.float32) / 10).astype(np.float32)


def grey(episode: int, frame: int) -> int:
    """The grey level of a frame: far apart from its neighbours', so a decoded frame says which it is."""
    return (episode * 37 + frame * 23) % 200 + 20


def frames(episode: int, length: int) -> Iterator[np.ndarray]:
    for frame in range(length):
        yield np.full((HEIGHT, WIDTH, 3), grey(episode, frame), dtype=np.uint8)


def episode(index: int, length: int, task: str = "pick the box") -> Episode:
    values = state(index, length)
    return Episode(
        index,
        task,
        length,
        {"observation.state": values, "action": values + 0.5},
        {"observation.images.front": frames(index, length)},
    )
