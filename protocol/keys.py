"""Every Zenoh key expression Convoy uses, in one place.

``convoy/<job>/exp/<actor>`` transitions · ``convoy/<job>/weights`` · ``convoy/<job>/ctl/<what>`` flow control and
commands · ``convoy/<job>/metrics/<role>/<id>`` · liveliness ``convoy/<job>/alive/<role>/<id>`` ·
``convoy/hosts/<host>/<what>`` host agents. Ids are checked here so that no caller can build a key with a wildcard
(``*``), a separator or Zenoh's reserved ``$`` in it.
"""

from __future__ import annotations

import re

PREFIX = "convoy"
ROLES = ("actor", "learner", "host", "supervisor", "api")
_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # fullmatch: "$" would let a trailing newline in


def check_id(value: str, what: str = "id") -> str:
    """``value`` if it is a safe key chunk (letters, digits, ``_ . -``; at most 64), else ValueError naming it."""
    if not isinstance(value, str) or not _ID.fullmatch(value):
        raise ValueError(
            f"{what} {value!r} cannot be part of a key expression: use 1–64 letters, digits, '_', '.' or '-', "
            "starting with a letter or digit"
        )
    return value


def job_root(job: str) -> str:
    return f"{PREFIX}/{check_id(job, 'job id')}"


def exp(job: str, actor: str) -> str:
    """Transition chunks published by one actor."""
    return f"{job_root(job)}/exp/{check_id(actor, 'actor id')}"


def exp_all(job: str) -> str:
    return f"{job_root(job)}/exp/*"


def weights(job: str) -> str:
    """Versioned policy weights published by the learner."""
    return f"{job_root(job)}/weights"


def ctl(job: str, what: str) -> str:
    """Control from the learner or supervisor (``budget`` for actor flow control, ``stop``)."""
    return f"{job_root(job)}/ctl/{check_id(what, 'control name')}"


def metrics(job: str, role: str, ident: str) -> str:
    return f"{job_root(job)}/metrics/{check_id(role, 'role')}/{check_id(ident, 'process id')}"


def metrics_all(job: str) -> str:
    return f"{job_root(job)}/metrics/**"


def alive(job: str, role: str, ident: str) -> str:
    """Liveliness token of one process of a job."""
    return f"{job_root(job)}/alive/{check_id(role, 'role')}/{check_id(ident, 'process id')}"


def alive_all(job: str) -> str:
    return f"{job_root(job)}/alive/**"


def parse_alive(key: object) -> tuple[str, str, str] | None:
    """``(job, role, id)`` of a liveliness key (a str or a Zenoh key expression: its ``str``), or None for a key
    that is not one."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != PREFIX or parts[2] != "alive":
        return None
    return parts[1], parts[3], parts[4]


def host(name: str, what: str) -> str:
    """A host agent's endpoint ``what``: ``cmd``, where it takes ``scale`` and ``stop`` commands."""
    return f"{PREFIX}/hosts/{check_id(name, 'host name')}/{check_id(what, 'host endpoint')}"
