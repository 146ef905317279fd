"""The rules language: a TOML rules file (`spec.py`), what it makes of a run's chunks (events and
metrics, `evaluate.py`), and what ingest calls as chunks arrive (`observe.py`). Pure: it reads
messages handed to it and writes nothing."""
