"""Many depot processes on one catalog: which one owns each hot run, and handing chunks to it."""
