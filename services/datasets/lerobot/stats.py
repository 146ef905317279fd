"""Feature statistics as LeRobot keeps them (policies normalise with them): per episode, then the
dataset's, weighted by frame count. Each feature gets min, max, mean, std, count and the quantiles
q01, q10, q50, q90, q99; vectors per dimension, images per channel in [0, 1] with shape (3, 1, 1)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
KEYS = ("min", "max", "mean", "std", "count", *(f"q{round(q * 100):02d}" for q in QUANTILES))

Stats = dict[str, np.ndarray]


def vector_stats(values: np.ndarray) -> Stats:
    """`values`: (n, D), or (n,) for a scalar column."""
    data = values.reshape(len(values), -1).astype(np.float64)
    out: Stats = {
        "min": data.min(axis=0),
        "max": data.max(axis=0),
        "mean": data.mean(axis=0),
        "std": data.std(axis=0),
        "count": np.array([len(values)]),
    }
    for q, key in zip(QUANTILES, KEYS[5:], strict=True):
        out[key] = np.quantile(data, q, axis=0)
    return out


def stats_sample(rgb: np.ndarray, target: int = 150, threshold: int = 300) -> np.ndarray:
    """A frame as image statistics take it: every k-th pixel of a frame 300 pixels or more on a side,
    k bringing its longer side near 150 (as LeRobot samples its images), so a sample of 100 frames
    stays a few MB at any resolution."""
    height, width = rgb.shape[:2]
    if max(height, width) < threshold:
        return rgb.copy()
    step = int(max(height, width) / target)
    return np.ascontiguousarray(rgb[::step, ::step])


def image_stats(frames: np.ndarray) -> Stats:
    """`frames`: (n, H, W, 3) uint8, a sample of an episode's frames: per channel, in [0, 1]."""
    channels = np.moveaxis(frames.astype(np.float64) / 255.0, -1, 0).reshape(frames.shape[-1], -1)
    out: Stats = {
        "min": channels.min(axis=1),
        "max": channels.max(axis=1),
        "mean": channels.mean(axis=1),
        "std": channels.std(axis=1),
        "count": np.array([len(frames)]),
    }
    for q, key in zip(QUANTILES, KEYS[5:], strict=True):
        out[key] = np.quantile(channels, q, axis=1)
    return {k: (v if k == "count" else v.reshape(-1, 1, 1)) for k, v in out.items()}


def aggregate(episodes: Iterable[Stats]) -> Stats:
    """The dataset's statistics from its episodes': min and max of theirs, means weighted by count,
    std by the parallel-variance formula, quantiles as count-weighted means (as LeRobot does)."""
    held = list(episodes)
    counts = np.array([float(s["count"][0]) for s in held])
    weights = (counts / counts.sum()).reshape(-1, *([1] * held[0]["mean"].ndim))
    means = np.stack([s["mean"] for s in held])
    mean = (means * weights).sum(axis=0)
    variance = ((np.stack([s["std"] for s in held]) ** 2 + (means - mean) ** 2) * weights).sum(axis=0)
    out: Stats = {
        "min": np.min(np.stack([s["min"] for s in held]), axis=0),
        "max": np.max(np.stack([s["max"] for s in held]), axis=0),
        "mean": mean,
        "std": np.sqrt(variance),
        "count": np.array([int(counts.sum())]),
    }
    for key in KEYS[5:]:
        out[key] = (np.stack([s[key] for s in held]) * weights).sum(axis=0)
    return out


def as_json(stats: Mapping[str, Stats]) -> dict[str, dict[str, Any]]:
    return {feature: {key: value.tolist() for key, value in s.items()} for feature, s in stats.items()}
