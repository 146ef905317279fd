"""Routine requests logged at DEBUG: a robot's agent polls the depot for pulls every few seconds
(FLEET_AGENT_PULL_POLL_S) and for its rules (FLEET_AGENT_RULES_POLL_S), reports a pull's progress
and, after each FileSink write, its copy of the run. At INFO those would be a line per poll on both
sides, drowning the lines that say what changed (a pull taken on or done, a run forwarded, a link
down), which stay at INFO."""

from __future__ import annotations

import logging

# Paths of the agent's routine calls, as access lines (depot) and request lines (agent) show them.
ROUTINE_PATHS = ("/v1/pulls", "/robot-copy", "GET /v1/rules HTTP/", '/v1/rules "')
# The loggers that write a line per routine event, and what marks one: uvicorn's access log (depot)
# and httpx (the agent's calls) a line per request; watchfiles a line per FileSink write the agent
# wakes up for ("1 change detected").
ROUTINE: dict[str, tuple[str, ...]] = {
    "uvicorn.access": ROUTINE_PATHS,
    "httpx": ROUTINE_PATHS,
    "watchfiles.main": ("change detected", "changes detected"),
}


class RoutineAtDebug(logging.Filter):
    """An INFO line of a routine event becomes a DEBUG line: dropped unless its logger logs DEBUG."""

    def __init__(self, marks: tuple[str, ...] = ROUTINE_PATHS) -> None:
        super().__init__()
        self.marks = marks

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.INFO or not any(mark in record.getMessage() for mark in self.marks):
            return True
        record.levelno, record.levelname = logging.DEBUG, logging.getLevelName(logging.DEBUG)
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


def quiet_routine_requests() -> None:
    """Install the filter on those loggers (once; the depot and the agent call this at start)."""
    for name, marks in ROUTINE.items():
        logger = logging.getLogger(name)
        if not any(isinstance(f, RoutineAtDebug) for f in logger.filters):
            logger.addFilter(RoutineAtDebug(marks))
