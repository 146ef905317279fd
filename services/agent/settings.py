"""`fleet agent`'s settings: its own, named `agent_*` (FLEET_AGENT_*, each also a flag without the
prefix), and the ingest settings it shares with the depot (`SharedSettings`: the spool is the
depot's hot tier and ingest run on the robot). Read once at start, as the depot's are, from the
environment, then the TOML file named by FLEET_CONFIG, then the defaults."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import NoDecode

from services.settings import Durability, Settings, SharedSettings, name_list


class AgentSettings(SharedSettings):
    """The robot agent's settings. Every field of its own starts with `agent_`: that prefix is how
    `fleet serve` tells the agent's keys in a shared TOML file from a typo of its own."""

    agent_spool: Path = Field(
        Path("./fleet-agent"), description="the agent's spool on the robot's disk: its runs and its state"
    )
    agent_listen: str = Field("127.0.0.1:9876", description="where the robot's SDK streams (GrpcSink URL .../proxy)")
    agent_status_addr: str = Field("127.0.0.1:9877", description="where the agent serves /metrics (Prometheus)")
    agent_depot: str = Field(
        "rerun+http://127.0.0.1:51234", description="the depot's gRPC address (rerun+http[s]://HOST:PORT)"
    )
    agent_api_url: str = Field("", description="the depot's REST API (default: http://DEPOT_HOST:8080)")
    agent_token: SecretStr | None = Field(None, description="the robot's ingest token (FLEET_TOKEN)")
    agent_retain_hours: float = Field(24.0, ge=0, description="runs the depot holds are kept on the robot this long")
    agent_max_bytes: int = Field(
        0, ge=0, description="the spool is kept under this size by deleting its oldest confirmed runs (0: no cap)"
    )
    agent_min_free_bytes: int = Field(
        256 << 20, ge=0, description="hard limit: with less free disk the agent refuses new data"
    )
    agent_bandwidth: str = Field("0", description="upload cap in bytes per second (500k, 2M; 0: none)")
    agent_bandwidth_rules: list[dict[str, Any]] = Field(
        default_factory=list,
        description="caps by time of day or network: TOML [[agent_bandwidth_rules]] tables of from, to, "
        "interface, bytes_per_s; the first that applies wins, else agent_bandwidth",
    )
    agent_live_include: Annotated[list[str], NoDecode] = Field(
        default_factory=lambda: ["/**"],
        description="entities forwarded live (the rest stays on the robot until pulled); "
        "a JSON list or comma-separated",
    )
    agent_live_exclude: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="entities never forwarded live; wins over agent_live_include"
    )
    agent_watch: Annotated[list[Path], NoDecode] = Field(
        default_factory=list,
        description="folders where the robot writes .rrd files (FileSink) and .mcap files (rosbag2) "
        "for the agent to send",
    )
    agent_file_idle_s: float = Field(30.0, gt=0, description="a watched file that stops growing this long is complete")
    agent_bag_idle_s: float = Field(
        30.0,
        gt=0,
        description="a watched .mcap file (rosbag2 or lone) that does not change this long is closed and uploaded, "
        "unless its metadata.yaml or next split and its footer said so sooner",
    )
    agent_check_s: float = Field(
        30.0, gt=0, description="how often the agent asks the depot which of the chunks it sent it holds"
    )
    agent_stall_s: float = Field(
        30.0, gt=0, description="a link that takes no data for this long is dropped and connected anew"
    )
    agent_pull_poll_s: float = Field(5.0, gt=0, description="how often the agent asks the depot for pulls")
    agent_pull_progress_s: float = Field(
        1.0, gt=0, description="while a pull is sent, how often its chunks and bytes so far are reported (if changed)"
    )
    agent_rules_poll_s: float = Field(
        15.0,
        gt=0,
        description="how often the agent asks the depot whether its rules changed (triggers run on the robot)",
    )
    agent_trigger_max_bytes_per_day: int = Field(
        0, ge=0, description="cap on the bytes all trigger windows send a day, over each trigger's own budget (0: none)"
    )
    agent_durability: Durability = Field(
        Durability.INTERVAL, description="spool fsync: always | interval (group_commit_ms) | off"
    )
    # The same variable as the depot's, for the agent's own refusal (see `fleet agent`'s port check).
    insecure: bool = Field(
        False,
        description="allow a non-loopback agent_listen or agent_status_addr: the agent takes data with no token "
        "and sends it on with the robot's, so anyone who reaches the port can write the robot's runs",
    )

    @field_validator("agent_live_include", "agent_live_exclude", "agent_watch", mode="before")
    @classmethod
    def _name_list(cls, value: Any) -> Any:
        return name_list(value)

    @classmethod
    def other_programs_key(cls, key: str) -> bool:
        return key in Settings.model_fields and key not in cls.model_fields


def load_agent_settings(**overrides: Any) -> AgentSettings:
    """Read the agent's settings once; `overrides` (its flags) win over everything."""
    return AgentSettings(**{k: v for k, v in overrides.items() if v is not None})
