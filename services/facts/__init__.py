"""What a run is, learnt from its messages and below both ingest and the sealed format: its facts
(`run.py`), its identity (robot, run id, date, secret fields: `identity.py`), and what is known of it
once sealed (`sealed.py`)."""
