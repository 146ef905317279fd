"""The catalog of robots, runs, entities and timelines (SQLAlchemy models and queries)."""
