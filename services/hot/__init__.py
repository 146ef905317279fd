"""The hot tier: runs being written, as append-only files on this node's disk (write, read, follow)."""
