"""The agent's Prometheus metrics (`http://AGENT_STATUS_ADDR/metrics`), read from the running agent
at each scrape."""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING

from prometheus_client import CollectorRegistry, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

if TYPE_CHECKING:
    from services.agent.service import Agent


class AgentCollector(Collector):
    def __init__(self, agent: Agent) -> None:
        self.agent = agent

    def collect(self) -> Iterator[Metric]:
        agent = self.agent
        runs = agent.spool.runs()
        progress = {run_id: sender.sent_until for run_id, sender in list(agent.runners.items())}
        saved = agent.state.runs()
        spool_bytes = sum(run.size for run in runs)
        backlog = sum(
            max(run.size - progress.get(run.run_id, 0), 0)
            for run in runs
            if not (saved.get(run.run_id) and saved[run.run_id].confirmed)
        )
        unconfirmed = sum(run.size for run in runs if not (saved.get(run.run_id) and saved[run.run_id].confirmed))
        yield GaugeMetricFamily("fleet_agent_spool_bytes", "Bytes of runs in the robot's spool", value=spool_bytes)
        yield GaugeMetricFamily("fleet_agent_backlog_bytes", "Spooled bytes not yet sent to the depot", value=backlog)
        yield GaugeMetricFamily(
            "fleet_agent_unconfirmed_bytes",
            "Spooled bytes of runs the depot has not confirmed sealed (never deleted by retention)",
            value=unconfirmed,
        )
        yield GaugeMetricFamily("fleet_agent_runs", "Runs in the spool", value=len(runs))
        yield GaugeMetricFamily("fleet_agent_link_up", "1 while the depot answers", value=int(agent.link.up))
        over = agent.retention.over_by if agent.retention else 0
        yield GaugeMetricFamily(
            "fleet_agent_spool_over_cap_bytes",
            "Bytes over agent_max_bytes that only unconfirmed runs hold (nothing can be deleted)",
            value=over,
        )
        cap = agent.bucket_cap()
        yield GaugeMetricFamily(
            "fleet_agent_bandwidth_cap_bytes_per_second", "The upload cap now (0: none)", value=cap or 0
        )
        sent = CounterMetricFamily(
            "fleet_agent_sent_bytes", "Bytes sent to the depot, by priority", labels=["priority"]
        )
        for priority, value in agent.bucket.sent_bytes.items():
            sent.add_metric([priority.name.lower()], value)
        yield sent
        counters = agent.forwarding.counters
        yield CounterMetricFamily(
            "fleet_agent_resent_bytes",
            "Chunk bytes sent again because the depot lacked them after a break",
            value=counters["bytes_resent"],
        )
        yield CounterMetricFamily(
            "fleet_agent_messages_sent", "Messages sent to the depot", value=counters["messages_sent"]
        )
        yield from _trigger_metrics(agent)
        yield from _bag_metrics(agent)


def _bag_metrics(agent: Agent) -> Iterator[Metric]:
    if agent.bags is None:
        return
    counts = agent.bags.counts
    states = GaugeMetricFamily(
        "fleet_agent_bags", "Watched MCAP files (rosbag2 bags): pending, uploaded, failed", labels=["state"]
    )
    for state in ("pending", "uploaded", "failed"):
        states.add_metric([state], getattr(counts, state))
    yield states
    yield CounterMetricFamily(
        "fleet_agent_bag_uploaded_bytes", "Bytes of MCAP files uploaded to the depot", value=counts.bytes_uploaded
    )


def _trigger_metrics(agent: Agent) -> Iterator[Metric]:
    triggers = agent.triggers
    yield CounterMetricFamily(
        "fleet_agent_triggers_fired",
        "Trigger windows fired by the rules on the robot",
        value=triggers.counters["fired"],
    )
    yield CounterMetricFamily(
        "fleet_agent_trigger_bytes_sent",
        "Bytes of trigger windows sent to the depot (each chunk once)",
        value=triggers.counters["bytes_sent"],
    )
    yield CounterMetricFamily(
        "fleet_agent_trigger_windows_over_budget",
        "Trigger windows held on the robot: over a day's budget",
        value=triggers.counters["over_budget"],
    )
    states = GaugeMetricFamily(
        "fleet_agent_trigger_windows", "Trigger windows on the robot, by state", labels=["state"]
    )
    counts: dict[str, int] = {}
    for window in list(triggers.windows.values()):
        counts[window.state] = counts.get(window.state, 0) + 1
    for state, count in sorted(counts.items()):
        states.add_metric([state], count)
    yield states
    yield GaugeMetricFamily(
        "fleet_agent_rules_version", "The rules version the robot runs (0: none)", value=agent.rules.version
    )
    refused = agent.rules.refused
    yield GaugeMetricFamily(
        "fleet_agent_rules_refused_version",
        "A newer rules version this agent cannot read (0: none); it keeps the version it runs",
        value=refused.version if refused else 0,
    )


def serve_metrics(agent: Agent, host: str, port: int) -> None:
    """Serve /metrics on a thread of its own (prometheus_client's server)."""
    registry = CollectorRegistry()
    registry.register(AgentCollector(agent))
    start_http_server(port, addr=host, registry=registry)
