"""The joint transition: the one declaration of what the acting loop records per env step.

A step of B envs with N agents is one transition per env; a chunk stacks T steps, ``[T, B, …]`` (a population's
``[T, R, B, …]`` in the acting loop, ``[T, R·B, …]`` on the wire). Every chunk holds the fields below with these
dtypes and per-step shapes (``N`` agents, ``D`` the observation width), plus whatever an algorithm's act adds
(``ActOutput.extras``: DIAL's heard messages, a memory module's history, the hierarchical agent's goals), which
its own ``observe`` reads. The acting loop builds transitions with :func:`record`, the wire requires these
fields in every chunk, the learner checks each chunk it receives against :func:`schema`, and the joint replay
refuses rows that do not hold it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Field:
    dtype: str  # numpy's dtype string
    shape: tuple[str, ...]  # per step, after the leading [T, B]: "N" agents, "D" observation width
    env_major: bool  # indexed by env (the env's arrays); False: by the act's [R, B] layout already
    doc: str


TRANSITION: dict[str, Field] = {
    "obs": Field("<f4", ("N", "D"), True, "each agent's observation the action was chosen on"),
    "action": Field("<i8", ("N",), False, "each agent's action"),
    "reward": Field("<f4", ("N",), True, "each agent's reward for the step"),
    "next_obs": Field("<f4", ("N", "D"), True, "the observation after the step (an ended episode's last one)"),
    "terminated": Field("|b1", (), True, "the episode ended in a terminal state: no bootstrap"),
    "truncated": Field("|b1", (), True, "the episode was cut at its step limit: bootstrap"),
    "episode": Field("<i8", (), True, "episodes of its run finished when this one began (SER's sample age)"),
}
ENV_MAJOR = tuple(name for name, f in TRANSITION.items() if f.env_major)


def record(
    obs: np.ndarray,
    action: np.ndarray,
    reward: np.ndarray,
    next_obs: np.ndarray,
    terminated: np.ndarray,
    truncated: np.ndarray,
    episode: np.ndarray,
    extras: dict[str, np.ndarray],
) -> dict[str, np.ndarray]:
    """One step's transition, each declared field in its declared dtype (no copy where it already is), then the
    act's extras."""
    core = {"obs": obs, "action": action, "reward": reward, "next_obs": next_obs, "terminated": terminated,
            "truncated": truncated, "episode": episode}  # fmt: skip
    out = {name: np.asarray(core[name], dtype=f.dtype) for name, f in TRANSITION.items()}
    clash = set(extras) & set(out)
    if clash:
        raise ValueError(f"extras {sorted(clash)}: an act's extras may not replace a transition field")
    return {**out, **extras}


def schema(n_agents: int, obs_dim: int) -> dict[str, tuple[str, tuple[int, ...]]]:
    """Field → (dtype, per-step shape) of the declared fields for an env of ``n_agents`` agents whose observations
    are ``obs_dim`` wide."""
    size = {"N": n_agents, "D": obs_dim}
    return {name: (f.dtype, tuple(size[s] for s in f.shape)) for name, f in TRANSITION.items()}
