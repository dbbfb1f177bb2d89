"""The joint transition: the one declaration of what the acting loop records per env step, and its type.

A step of B envs with N agents is one transition per env; a chunk stacks T steps, ``[T, B, …]`` (a population's
``[T, R, B, …]`` in the acting loop, ``[T, R·B, …]`` on the wire), the replay holds rows ``[R, rows, …]`` and
samples batches ``[R, M, …]`` (DIAL's sequences ``[R, T, B, …]``). Whatever its leading dims, a
:class:`Transition` holds the declared fields with their dtypes and per-step shapes after those dims (``N`` agents,
``D`` the observation width), plus in ``extras`` what an algorithm's act adds (``ActOutput.extras``: DIAL's heard
messages, a memory module's history, the hierarchical agent's goals) or its replay derives (n-step returns'
``discount``), which its own ``observe`` and ``loss`` read. The acting loop builds transitions with :func:`record`,
the wire carries them (``protocol.wire``: the one place they are a map of names), the learner checks each chunk it
receives against :func:`schema`, the joint replay refuses rows that do not hold it, and the losses read the fields
as attributes.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Generic, TypeVar

import numpy as np

A = TypeVar("A")  # the arrays: numpy's on the host (acting, the wire), torch's on the device (replay, losses)
B = TypeVar("B")


@dataclass(frozen=True)
class Field:
    dtype: str  # numpy's dtype string
    shape: tuple[str, ...]  # per step, after the leading dims: "N" agents, "D" observation width
    doc: str


def declared(dtype: str, shape: tuple[str, ...], doc: str) -> dict[str, Field]:
    """A field's declaration, kept in its dataclass field's metadata (``TRANSITION`` reads it back)."""
    return {"declared": Field(dtype, shape, doc)}


@dataclass(frozen=True, eq=False)
class Transition(Generic[A]):
    """One or many joint transitions, leading dims ``[*lead]`` shared by every field (``[T, R, B]`` a population's
    chunk, ``[R, M]`` a sampled batch), then each field's per-step shape."""

    obs: A = field(metadata=declared("<f4", ("N", "D"), "each agent's observation the action was chosen on"))
    action: A = field(metadata=declared("<i8", ("N",), "each agent's action"))
    reward: A = field(metadata=declared("<f4", ("N",), "each agent's reward for the step"))
    next_obs: A = field(metadata=declared("<f4", ("N", "D"), "the observation after the step (an episode's last one)"))
    terminated: A = field(metadata=declared("|b1", (), "the episode ended in a terminal state: no bootstrap"))
    truncated: A = field(metadata=declared("|b1", (), "the episode was cut at its step limit: bootstrap"))
    episode: A = field(metadata=declared("<i8", (), "episodes of its run finished when this one began (SER's age)"))
    extras: dict[str, A] = field(default_factory=dict)  # the algorithm's own fields, same leading dims

    def columns(self) -> dict[str, A]:
        """Every field by name, the declared ones first: for code that treats all fields alike (the wire's map,
        the replay's storage and files)."""
        return {**{name: getattr(self, name) for name in TRANSITION}, **self.extras}

    def map(self, fn: Callable[[A], B]) -> Transition[B]:
        """``fn`` applied to every field (a reshape, a slice, a copy to the device)."""
        return from_columns({name: fn(v) for name, v in self.columns().items()})


TRANSITION: dict[str, Field] = {f.name: f.metadata["declared"] for f in fields(Transition) if f.metadata}


def from_columns(columns: Mapping[str, A]) -> Transition[A]:
    """The transition whose fields are ``columns`` (the declared ones, the rest its extras): the inverse of
    :meth:`Transition.columns`. A declared field missing is a ``KeyError`` naming it."""
    missing = [name for name in TRANSITION if name not in columns]
    if missing:
        raise KeyError(f"transition fields {missing} missing (convoy.transition)")
    extras = {k: v for k, v in columns.items() if k not in TRANSITION}
    return Transition(**{name: columns[name] for name in TRANSITION}, extras=extras)


def stack(steps: Sequence[Transition[np.ndarray]]) -> Transition[np.ndarray]:
    """Steps ``[*lead]`` as one chunk ``[T, *lead]``."""
    cols = [s.columns() for s in steps]
    return from_columns({name: np.stack([c[name] for c in cols]) for name in cols[0]})


def record(
    obs: np.ndarray,
    action: np.ndarray,
    reward: np.ndarray,
    next_obs: np.ndarray,
    terminated: np.ndarray,
    truncated: np.ndarray,
    episode: np.ndarray,
    extras: dict[str, np.ndarray],
) -> Transition[np.ndarray]:
    """One step's transition, each declared field in its declared dtype (no copy where it already is), then the
    act's extras."""
    clash = set(extras) & set(TRANSITION)
    if clash:
        raise ValueError(f"extras {sorted(clash)}: an act's extras may not replace a transition field")
    step = Transition(obs, action, reward, next_obs, terminated, truncated, episode)
    return from_columns({**{k: np.asarray(v, dtype=TRANSITION[k].dtype) for k, v in step.columns().items()}, **extras})


def schema(n_agents: int, obs_dim: int) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Field → (dtype, per-step shape) of the declared fields for an env of ``n_agents`` agents whose observations
    are ``obs_dim`` wide."""
    size = {"N": n_agents, "D": obs_dim}
    return {name: (f.dtype, tuple(size[s] for s in f.shape)) for name, f in TRANSITION.items()}
