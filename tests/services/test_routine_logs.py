"""A robot's routine calls (pull polls every FLEET_AGENT_PULL_POLL_S, progress and copy reports
after each FileSink write) are DEBUG lines on the depot's access log and the agent's request log;
other requests stay at INFO."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import pytest

from services.routine_logs import quiet_routine_requests

ACCESS = '%s - "%s %s HTTP/%s" %d'  # uvicorn's access line
REQUEST = 'HTTP Request: %s %s "%s %d %s"'  # httpx's


class Kept(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.lines: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append((record.levelname, record.getMessage()))


@pytest.fixture
def kept() -> Iterator[Kept]:
    handler = Kept()
    loggers = [logging.getLogger(name) for name in ("uvicorn.access", "httpx", "watchfiles.main")]
    saved = [(lg.level, list(lg.filters)) for lg in loggers]
    for lg in loggers:
        lg.addHandler(handler)
        lg.setLevel(logging.INFO)
    quiet_routine_requests()  # what `fleet serve` and `fleet agent` do at start
    yield handler
    for lg, (level, filters) in zip(loggers, saved, strict=True):
        lg.removeHandler(handler)
        lg.setLevel(level)
        lg.filters = filters


def test_polls_and_reports_are_not_info_lines(kept: Kept):
    access, agent = logging.getLogger("uvicorn.access"), logging.getLogger("httpx")
    access.info(ACCESS, "127.0.0.1:5", "GET", "/v1/pulls?state=pending", "1.1", 200)
    access.info(ACCESS, "127.0.0.1:5", "PUT", "/v1/runs/run-1/robot-copy", "1.1", 200)
    access.info(ACCESS, "127.0.0.1:5", "POST", "/v1/pulls/pull-1/progress", "1.1", 200)
    agent.info(REQUEST, "GET", "http://depot/v1/pulls?state=sending", "HTTP/1.1", 200, "OK")
    access.info(ACCESS, "127.0.0.1:5", "GET", "/v1/rules", "1.1", 200)  # the rules poll
    agent.info(REQUEST, "GET", "http://depot/v1/rules", "HTTP/1.1", 200, "OK")
    assert kept.lines == []  # DEBUG, and these loggers log INFO
    access.info(ACCESS, "127.0.0.1:5", "GET", "/v1/runs/run-1", "1.1", 200)
    access.warning(ACCESS, "127.0.0.1:5", "GET", "/v1/pulls", "1.1", 500)
    access.info(ACCESS, "127.0.0.1:5", "PUT", "/v1/rules", "1.1", 200)  # a person applying rules
    access.info(ACCESS, "127.0.0.1:5", "GET", "/v1/rules/history", "1.1", 200)
    assert [level for level, _ in kept.lines] == ["INFO", "WARNING", "INFO", "INFO"]


def test_at_debug_they_are_shown_as_debug(kept: Kept):
    logging.getLogger("httpx").setLevel(logging.DEBUG)
    logging.getLogger("httpx").info(REQUEST, "GET", "http://depot/v1/pulls?state=pending", "HTTP/1.1", 200, "OK")
    assert [level for level, _ in kept.lines] == ["DEBUG"]


def test_a_filesink_write_the_agent_wakes_up_for_is_no_info_line(kept: Kept):
    """watchfiles says "1 change detected" at INFO on every write of a watched recording."""
    watch = logging.getLogger("watchfiles.main")
    watch.info("%d change%s detected", 1, "")
    watch.info("%d change%s detected", 3, "s")
    assert kept.lines == []
    watch.warning("rust notify error")
    assert [level for level, _ in kept.lines] == ["WARNING"]
