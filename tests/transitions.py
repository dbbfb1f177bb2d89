"""Transitions for tests: the declared fields a test does not care about filled with zeros."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from convoy.transition import TRANSITION, Transition, from_columns


def filled(lead: tuple[int, ...], **columns: np.ndarray) -> Transition[np.ndarray]:
    """A transition of ``columns`` (declared fields, or extras), every declared field not given zeros ``[*lead]`` of
    its dtype: rows for a replay that holds no declared schema."""
    return from_columns({**{k: np.zeros(lead, f.dtype) for k, f in TRANSITION.items()}, **columns})


def batch(**columns: Tensor) -> Transition[Tensor]:
    """A batch of ``columns`` (declared fields, or extras): ``truncated`` and ``episode``, when not given, zeros like
    ``terminated`` (the losses read neither, but for SER's ``episode`` and DIAL's ``truncated``); any other declared
    field not given empty (a test of a part that does not read it)."""
    done = columns.get("terminated", torch.zeros(0, dtype=torch.bool))
    empty = {k: torch.zeros(0) for k in TRANSITION}
    zeros = {"truncated": torch.zeros_like(done), "episode": torch.zeros_like(done, dtype=torch.int64)}
    return from_columns({**empty, **zeros, **columns})


def run_of(chunk: Transition[np.ndarray], k: int) -> Transition[np.ndarray]:
    """Run k's share ``[T, B, …]`` of a population's chunk ``[T, R, B, …]``: what the single run of its seed sees."""
    return chunk.map(lambda v: v[:, k])
