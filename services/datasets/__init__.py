"""Dataset snapshots: a selection of runs (and windows around their events) resolved into an
immutable version `NAME@N` listing its episodes and the chunks each reads."""
