"""Datasets for training: a selection of runs (and windows around their events) resolved into an
immutable snapshot version `NAME@N` listing its episodes and the chunks each reads, and its export
(`lerobot/`: the LeRobot v3.0 format)."""
