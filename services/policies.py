"""Retention policies: how long a run stays warm, then cold, before it is deleted.

A run's age is counted from its end (its last data). It is archived (warm -> cold) once older
than `warm_days`, and deleted once older than `warm_days + cold_days`, unless pinned. With
`cold_days = 0` a run goes straight from warm to deleted. The default policy applies unless an
override names the run's robot (first choice) or its application.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from pydantic import BaseModel, ConfigDict, Field, model_validator


class PolicyOverride(BaseModel):
    """`[[retention_policies]]` in the TOML settings, or a JSON list in FLEET_RETENTION_POLICIES."""

    model_config = ConfigDict(extra="forbid")  # a misspelt field must not fall back to the default's days

    name: str = Field(description="shown in the tombstone of every run it deletes")
    robot: str | None = Field(None, description="applies to this robot's runs")
    application: str | None = Field(None, description="applies to runs of this application id")
    warm_days: float | None = Field(None, ge=0, description="days warm before archiving (default: the default's)")
    cold_days: float | None = Field(None, ge=0, description="days cold before deletion (default: the default's)")

    @model_validator(mode="after")
    def _names_a_target(self) -> PolicyOverride:
        if (self.robot is None) == (self.application is None):
            raise ValueError(f"retention policy {self.name!r} must name exactly one of robot or application")
        return self


@dataclass(frozen=True)
class Policy:
    name: str
    warm_days: float
    cold_days: float

    @property
    def archive_after(self) -> dt.timedelta:
        return dt.timedelta(days=self.warm_days)

    @property
    def delete_after(self) -> dt.timedelta:
        return dt.timedelta(days=self.warm_days + self.cold_days)

    def to_dict(self) -> dict[str, object]:
        return {"name": self.name, "warm_days": self.warm_days, "cold_days": self.cold_days}


@dataclass(frozen=True)
class Policies:
    default: Policy
    overrides: tuple[PolicyOverride, ...] = ()

    def for_run(self, robot_id: str, application_id: str) -> Policy:
        """The policy of a run: an override for its robot, else for its application, else the default."""
        match = next((o for o in self.overrides if o.robot == robot_id), None) or next(
            (o for o in self.overrides if o.application == application_id), None
        )
        return self.default if match is None else self._resolved(match)

    def _resolved(self, override: PolicyOverride) -> Policy:
        return Policy(
            override.name,
            self.default.warm_days if override.warm_days is None else override.warm_days,
            self.default.cold_days if override.cold_days is None else override.cold_days,
        )

    def to_dict(self) -> dict[str, object]:
        return {
            "default": self.default.to_dict(),
            "overrides": [{**o.model_dump(exclude_none=True), **self._resolved(o).to_dict()} for o in self.overrides],
        }
