"""What the depot knows of robots' own tiers: which chunks it holds of their runs (`held.py`), pulls
queued for their agents (`pulls.py`), and what their agents report holding (`copies.py`)."""
