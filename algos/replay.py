"""The joint replay buffer: a preallocated numpy ring of whole joint transitions.

Centralized algorithms need every agent's view of the same step, so one row holds all agents' observations at t
and t+1, their actions and rewards, the termination flag and the episode id (what stabilised experience replay
weighs by), plus whatever else an algorithm asked to keep (a fingerprint, received messages). Rows are written
and read as whole slices, never one element at a time; arrays are allocated on the first insert, from its
shapes and dtypes, and never grow past ``capacity``.

A population of R runs keeps R rings in one array ``[R, capacity, …]``: its runs insert the same number of rows at
the same times, so one write pointer serves all, and a sample draws each run's indices from that run's own stream.
"""

from __future__ import annotations

import numpy as np


class JointReplay:
    """Fixed-capacity ring of transitions; ``add`` takes any number of rows, ``sample`` returns a dict of arrays."""

    def __init__(self, capacity: int, runs: int | None = None) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: must be ≥ 1 (got {capacity})")
        self.capacity = capacity
        self.runs = runs
        self._data: dict[str, np.ndarray] = {}
        self._next = 0
        self._size = 0

    def __len__(self) -> int:
        return self._size

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self._data.values())

    def add(self, rows: dict[str, np.ndarray]) -> None:
        """Append rows (every array shares the leading dim M; a population's ``[R, M, …]``); the oldest rows are
        overwritten when full."""
        if self.runs is not None:
            rows = {k: np.moveaxis(np.asarray(v), 0, 1) for k, v in rows.items()}  # [M, R, …] for the ring logic
        sizes = {k: len(v) for k, v in rows.items()}
        m = next(iter(sizes.values()))
        if any(s != m for s in sizes.values()):
            raise ValueError(f"rows: every field needs the same leading size, got {sizes}")
        if not self._data:
            self._data = {k: self._allocate(np.asarray(v)) for k, v in rows.items()}
        elif set(rows) != set(self._data):
            raise ValueError(f"rows: fields {sorted(rows)} differ from the buffer's {sorted(self._data)}")
        if m > self.capacity:  # only the newest rows can survive
            rows = {k: v[-self.capacity :] for k, v in rows.items()}
            m = self.capacity
        first = min(m, self.capacity - self._next)  # up to the end of the ring, then the wrapped rest: 2 slices
        for k, v in rows.items():
            buf = self._data[k] if self.runs is None else np.moveaxis(self._data[k], 0, 1)  # a view [cap, R, …]
            buf[self._next : self._next + first] = v[:first]
            buf[: m - first] = v[first:]
        self._next = (self._next + m) % self.capacity
        self._size = min(self._size + m, self.capacity)

    def _allocate(self, v: np.ndarray) -> np.ndarray:
        if self.runs is None:
            return np.zeros((self.capacity, *v.shape[1:]), dtype=v.dtype)
        return np.zeros((v.shape[1], self.capacity, *v.shape[2:]), dtype=v.dtype)

    def sample(self, n: int, rng: np.random.Generator | list[np.random.Generator]) -> dict[str, np.ndarray]:
        """``n`` rows drawn uniformly with replacement; a population's ``[R, n, …]``, run k's rows drawn by
        ``rng[k]`` exactly as a single run's buffer would draw them."""
        if self._size == 0:
            raise ValueError("sample() from an empty replay buffer")
        if self.runs is None:
            idx = rng.integers(0, self._size, size=n)  # type: ignore[union-attr]
            return {k: v[idx] for k, v in self._data.items()}
        idx = np.stack([g.integers(0, self._size, size=n) for g in rng])  # type: ignore[union-attr]
        run = np.arange(self.runs)[:, None]
        return {k: v[run, idx] for k, v in self._data.items()}

    def state_dict(self) -> dict:
        """Contents for a full checkpoint (only the filled part)."""
        filled = np.s_[: self._size] if self.runs is None else np.s_[:, : self._size]
        return {"data": {k: v[filled].copy() for k, v in self._data.items()}, "next": self._next}

    def load_state_dict(self, state: dict) -> None:
        self._data, self._size, self._next = {}, 0, 0
        if state["data"]:
            self.add(state["data"])
            self._next = state["next"] % self.capacity
