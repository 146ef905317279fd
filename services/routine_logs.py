"""Routine requests logged at DEBUG: a robot's agent polls the depot for pulls every few seconds
(FLEET_AGENT_PULL_POLL_S), reports a pull's progress and, after each FileSink write, its copy of
the run. At INFO those would be a line per poll on both sides, drowning the lines that say what
changed (a pull taken on or done, a run forwarded, a link down), which stay at INFO."""

from __future__ import annotations

import logging

# Paths of the agent's routine calls, as access lines (depot) and request lines (agent) show them.
ROUTINE_PATHS = ("/v1/pulls", "/robot-copy")
# The loggers that write a line per request: uvicorn's access log (depot), httpx (the agent's calls).
REQUEST_LOGGERS = ("uvicorn.access", "httpx")


class RoutineAtDebug(logging.Filter):
    """An INFO line of a routine request becomes a DEBUG line: dropped unless its logger logs DEBUG."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.INFO or not any(path in record.getMessage() for path in ROUTINE_PATHS):
            return True
        record.levelno, record.levelname = logging.DEBUG, logging.getLevelName(logging.DEBUG)
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


def quiet_routine_requests() -> None:
    """Install the filter on the request loggers (once; the depot and the agent call this at start)."""
    for name in REQUEST_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RoutineAtDebug) for f in logger.filters):
            logger.addFilter(RoutineAtDebug())
