"""The bottom layer: errors and their status table, ids, the clock and the states a run can be in.

Everything may import it (the catalog, the client, every service); it imports nothing of ours."""
