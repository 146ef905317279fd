"""What the export benchmark's robots log, as formulas both sides use: a camera image per tick (a
gradient with a bar that moves, so frames differ and compress as camera frames do), 7 joint values
and 7 commands per scalar tick. numpy only: the lerobot venv loads this file by path."""

from __future__ import annotations

import numpy as np

JOINTS = 7
SCALAR_HZ = 100
CAMERA_HZ = 30


def image(tick: int, width: int, height: int) -> np.ndarray:
    x = np.arange(width, dtype=np.uint16)[None, :]
    y = np.arange(height, dtype=np.uint16)[:, None]
    out = np.empty((height, width, 3), dtype=np.uint8)
    out[:, :, 0] = (x + tick) % 256
    out[:, :, 1] = (y * 2 + tick) % 256
    out[:, :, 2] = 128
    bar = (tick * 4) % width
    out[:, bar : bar + 16, :] = 255
    return out


def joints(run: int, tick: int) -> list[float]:
    return [float(np.sin(tick / 100 + j + run)) for j in range(JOINTS)]


def command(run: int, tick: int) -> list[float]:
    return [v + 0.01 for v in joints(run, tick)]
