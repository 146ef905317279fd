"""The fleet as a corpus: what rules make of runs (events, metrics), people's events and tags."""
