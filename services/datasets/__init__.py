"""Datasets for training: snapshots of runs and their export."""
