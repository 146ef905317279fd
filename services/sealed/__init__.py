"""The sealed-run format (recording.rrd, chunks.parquet, run.json), written at promotion and read
by serving, and the tiers that hold it."""
