"""What fixes an error, said in the words of whoever asked. A ``Fix`` is its words with a slot (``{}``) for each
``Step``, a request of this API that helps (list the jobs, resume this one with 4 actors). The API says a step as its
route, ``POST /jobs/x/resume {"actors": 4}``; the command line as the convoy command that sends it, ``convoy jobs
resume x --actors 4`` (a body field is the flag of its name: ``num_envs`` is ``--num-envs``, as the flags drawn from
the config models are named). A client asks for the command line's words with the request header ``Convoy-Words:
cli``; the error body keeps its one shape, ``{"field", "problem", "fix"}``, either way.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal

from convoy.validation import ConfigError, flag_name

WORDS_HEADER = "Convoy-Words"
Words = Literal["api", "cli"]


def words_of(header: str | None) -> Words:
    """The words a request asked for in its ``Convoy-Words`` header: ``cli``, else the API's own."""
    return "cli" if (header or "").strip().lower() == "cli" else "api"


# Each route a fix names, with the convoy command that sends it ({id}: the job's or sweep's id) and what to read in
# its answer where it shows more than the route's; None where no command does (the command line says the route).
COMMANDS: dict[str, tuple[str, str] | None] = {
    "GET /jobs": ("convoy jobs list", ""),
    "GET /jobs/{id}": ("convoy jobs status {id}", ""),
    "POST /jobs/{id}/resume": ("convoy jobs resume {id}", ""),
    "GET /jobs/{id}/logs": ("convoy jobs logs {id}", ""),
    "GET /jobs/{id}/metrics": ("convoy jobs metrics {id}", ""),
    "GET /jobs/{id}/checkpoints": ("convoy jobs status {id}", "its last checkpoint"),
    "GET /jobs/{id}/evaluations": None,
    "GET /sweeps": ("convoy sweep list", ""),
    "GET /sweeps/{id}": ("convoy sweep status {id}", ""),
    "GET /envs": ("convoy env list --params", ""),
    "GET /algos": ("convoy algos", ""),
}


@dataclass(frozen=True)
class Step:
    """One request that helps: ``route`` (a key of ``COMMANDS``) for the job or sweep ``id`` (None: any, said
    ``{id}`` by the API and ``ID`` by the command line) with ``body``."""

    route: str
    id: str | None = None
    body: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.route not in COMMANDS:
            raise KeyError(f"{self.route!r} is not a route a fix names; add it to COMMANDS")

    def say(self, words: Words) -> str:
        command = COMMANDS[self.route]
        if words == "cli" and command is not None:
            line, note = command
            args = [line.replace("{id}", self.id or "ID"), *(f"{flag_name(k)} {v}" for k, v in self.body.items())]
            return f"`{' '.join(args)}`" + (f" ({note})" if note else "")
        route = self.route.replace("{id}", self.id or "{id}")
        return f"{route} {json.dumps(dict(self.body))}" if self.body else route


@dataclass(frozen=True)
class Fix:
    """What to do: ``text`` with one ``{}`` per step, each said in the words asked for."""

    text: str
    steps: tuple[Step, ...] = ()

    def __init__(self, text: str, *steps: Step) -> None:
        if text.count("{}") != len(steps):
            raise ValueError(f"{text!r} has {text.count('{}')} slots for {len(steps)} steps")
        object.__setattr__(self, "text", text)
        object.__setattr__(self, "steps", steps)

    def say(self, words: Words = "api") -> str:
        head, *rest = self.text.split("{}")
        return head + "".join(step.say(words) + text for step, text in zip(self.steps, rest, strict=True))

    def of_job(self, job_id: str | None) -> Fix:
        """This fix for one job: its job steps that name no id name ``job_id`` (None: as they are)."""
        if job_id is None:
            return self
        mine = (replace(s, id=job_id) if s.id is None and " /jobs/{id}" in s.route else s for s in self.steps)
        return Fix(self.text, *mine)


class ConfigRefusal(ConfigError):
    """A ConfigError (a 422 naming ``field``) whose fix is not the usual "change this field"."""

    def __init__(self, field: str, message: str, fix: Fix) -> None:
        super().__init__(field, message)
        self.fix = fix
