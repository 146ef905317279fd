"""A dataset version written as a LeRobot v3.0 dataset: Parquet frames, an MP4 per camera and
episode, and the `meta/` files LeRobot's loader reads (see `layout.py`)."""
