"""The robot-side agent: forwards a robot's Rerun data to the depot (live, backfill, pulls) and keeps its own spool."""
