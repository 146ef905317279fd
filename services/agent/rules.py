"""The depot's rules as the agent runs them: fetched with the robot's token (`GET /v1/rules`), kept
in the spool (`SPOOL/rules.json`) so a restart while the depot is unreachable works with the last
copy, and refreshed every `agent_rules_poll_s` when the depot's version changed.

A version the agent cannot read (a newer rules language than this agent's, say) is not taken: the
agent keeps the version it runs and says why, in its log once, in `fleet agent status` and in
`fleet_agent_rules_refused_version`.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from core.errors import InvalidRulesError
from services.rules.spec import RuleSet, parse_rules

log = logging.getLogger("fleet.agent")

RULES_FILE = "rules.json"


@dataclass(frozen=True)
class Refusal:
    version: int
    why: str


def on_the_robot(rules: RuleSet) -> RuleSet:
    """What the robot evaluates of a rule set: the event rules its triggers name (metrics and other
    events are the depot's), and the triggers."""
    named = {name for trigger in rules.triggers for name in trigger.events}
    return RuleSet(events=tuple(r for r in rules.events if r.name in named), triggers=rules.triggers, text=rules.text)


class AgentRules:
    """The rules in force on the robot: `rules` (empty until a version was read) and its `version`
    (0: none yet)."""

    def __init__(self, spool: Path) -> None:
        self.path = spool / RULES_FILE
        self.rules = RuleSet.empty()
        self.version = 0
        self.refused: Refusal | None = None
        self.changes = 0  # counts versions taken, so evaluators know to start again
        self._load()

    def _load(self) -> None:
        try:
            saved = json.loads(self.path.read_text())
            rules = on_the_robot(parse_rules(str(saved["text"])))
            version = int(saved["version"])
        except FileNotFoundError:
            return
        except (OSError, ValueError, KeyError, TypeError, InvalidRulesError) as exc:
            log.warning("the rules kept in %s cannot be read (%s): waiting for the depot's", self.path, exc)
            return
        self.rules, self.version = rules, version
        log.info("rules: version %d, kept from the last time the depot answered", version)

    def take(self, answer: dict[str, Any]) -> bool:
        """The depot's answer to `GET /v1/rules`: taken if it is a newer version this agent can read
        (saved in the spool first); whether the rules in force changed."""
        version = int(answer.get("version") or 0)
        if version == self.version or (self.refused is not None and self.refused.version == version):
            return False
        text = str(answer.get("text") or "")
        try:
            rules = on_the_robot(parse_rules(text)) if version else RuleSet.empty()
        except InvalidRulesError as exc:
            self.refused = Refusal(version, str(exc))
            log.warning(
                "rules version %d cannot be read by this agent (%s): it keeps version %d; upgrade the agent",
                version,
                exc,
                self.version,
            )
            return False
        self._save(version, text)
        self.rules, self.version, self.refused = rules, version, None
        self.changes += 1
        log.info("rules: now version %d (%d triggers)", version, len(rules.triggers))
        return True

    def _save(self, version: int, text: str) -> None:
        """Written whole then renamed, so a kill leaves the old copy or the new one."""
        temporary = self.path.with_suffix(".tmp")
        temporary.write_text(json.dumps({"version": version, "text": text}))
        os.replace(temporary, self.path)

    def status(self) -> dict[str, Any]:
        return {
            "version": self.version,
            "triggers": len(self.rules.triggers),
            "refused_version": self.refused.version if self.refused else None,
            "refused_why": self.refused.why if self.refused else None,
        }
