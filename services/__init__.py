"""Server side of the fleet depot: the RRD codec, ingest, serving, retention, settings and errors."""

__version__ = "0.1.0"
