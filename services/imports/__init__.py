"""Imports: every upload (an `.rrd` file, or an MCAP file converted by the Rerun CLI) from its first
byte to its filed runs, with its state in the catalog, and failed MCAP originals in quarantine."""
