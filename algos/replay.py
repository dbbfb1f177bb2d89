"""The joint replay buffer: a preallocated numpy ring of whole joint transitions.

Centralized algorithms need every agent's view of the same step, so one row holds all agents' observations at t
and t+1, their actions and rewards, the termination flag and the episode id (what stabilised experience replay
weighs by), plus whatever else an algorithm asked to keep (a fingerprint, received messages). Rows are written
and read as whole slices, never one element at a time; arrays are allocated on the first insert, from its
shapes and dtypes, and never grow past ``capacity``. Given the declared transition (``convoy.transition.schema``),
every insert is held to it: a declared field missing, or of another dtype or shape, is refused with its name.

``capacity`` is where the ring wraps; the arrays hold only the rows a run can store, ``reserve(rows)``: a run of
S env steps never stores more than about S rows, so a 20 k-step run with the treadmill's 1 M capacity allocates
20 k rows, not 1 M (1.2 GB). Should more come (a resumed run past its budget), the arrays grow, up to ``capacity``.
Until a ring wraps its rows sit at 0 … size − 1 whatever its allocation, and samples draw ``[0, size)``: a run
that fits reads and samples exactly what it did with every row allocated up front.

A population of R runs keeps R rings in one array ``[R, rows, …]``, each with its own write pointer and size:
usually every run inserts the same rows at the same times, but a hierarchical meta-controller gets a transition only
where an option ended, so ``add(rows, valid)`` inserts each run's valid rows only. A sample draws each run's indices
from that run's own stream, over that run's own rows, exactly as its single run's buffer would.
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np


class JointReplay:
    """Fixed-capacity ring of transitions; ``add`` takes any number of rows, ``sample`` returns a dict of arrays."""

    def __init__(
        self, capacity: int, runs: int | None = None, declared: dict[str, tuple[str, tuple[int, ...]]] | None = None
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity: must be ≥ 1 (got {capacity})")
        self.capacity = capacity
        self.runs = runs
        self.declared = declared or {}  # field → (dtype, per-row shape) every insert must hold
        self._data: dict[str, np.ndarray] = {}
        self._reserve = capacity  # rows allocated at the first insert (``reserve``)
        self._next = np.zeros(runs or (), dtype=np.int64)  # a population's per run [R]
        self._size = np.zeros(runs or (), dtype=np.int64)

    def __len__(self) -> int:
        """Rows held (a population's: the fewest any run holds)."""
        return int(self._size.min())

    @property
    def nbytes(self) -> int:
        """Bytes allocated (a population's: all runs')."""
        return sum(a.nbytes for a in self._data.values())

    @property
    def allocated(self) -> int:
        """Rows allocated per run: ``capacity`` once the ring has wrapped, up to then as few as ``reserve`` asked."""
        if not self._data:
            return 0
        first = next(iter(self._data.values()))
        return int(first.shape[0 if self.runs is None else 1])

    def reserve(self, rows: int) -> None:
        """Allocate ``rows`` per run (at most ``capacity``) instead of ``capacity``: the most this run will store.
        A buffer holding data grows to it at once; more rows than reserved grow it later (by half or to what they
        need, at most ``capacity``), so a short reserve costs a copy, never a row."""
        if rows < 1:
            raise ValueError(f"rows: must be ≥ 1 (got {rows})")
        self._reserve = min(int(rows), self.capacity)
        if self._data and self.allocated < self._reserve:
            self._grow(self._reserve)

    def _room(self, reach: int) -> None:
        """Rows up to ``reach`` (≤ capacity) are about to be written: grow when they are not allocated — by half at
        least, so rows arriving one chunk at a time past a short reserve cost few copies."""
        held = self.allocated
        if reach > held:
            self._grow(min(max(reach, held + held // 2), self.capacity))

    def _grow(self, rows: int) -> None:
        """Reallocate every field to ``rows`` per run, keeping the rows held in their places. Only an allocation
        short of ``capacity`` grows, and such a ring has not wrapped: its rows are 0 … size − 1, where they stay."""
        held = self.allocated
        for k, v in self._data.items():
            new = np.zeros((rows, *v.shape[1:]) if self.runs is None else (v.shape[0], rows, *v.shape[2:]), v.dtype)
            new[np.s_[:held] if self.runs is None else np.s_[:, :held]] = v
            self._data[k] = new

    def add(self, rows: dict[str, np.ndarray], valid: np.ndarray | None = None) -> None:
        """Append rows (every array shares the leading dim M; a population's ``[R, M, …]``); the oldest rows are
        overwritten when full. ``valid [R, M]`` (a population): only those rows, each run's in order, to its ring."""
        self._check_declared(rows)
        if self.runs is not None and (valid is not None or (self._next != self._next[0]).any()):
            self._add_valid(rows, np.ones(np.shape(next(iter(rows.values())))[:2], bool) if valid is None else valid)
            return
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
        at = int(self._next.flat[0])  # one pointer for all runs here
        self._room(min(at + m, self.capacity))
        first = min(m, self.capacity - at)  # up to the end of the ring, then the wrapped rest: 2 slices
        for k, v in rows.items():
            buf = self._data[k] if self.runs is None else np.moveaxis(self._data[k], 0, 1)  # a view [cap, R, …]
            buf[at : at + first] = v[:first]
            buf[: m - first] = v[first:]
        self._next = (self._next + m) % self.capacity
        self._size = np.minimum(self._size + m, self.capacity)

    def _check_declared(self, rows: dict[str, np.ndarray]) -> None:
        lead = 1 if self.runs is None else 2
        for name, (dtype, shape) in self.declared.items():
            if name not in rows:
                raise ValueError(f"rows: no {name!r}, a field of the declared transition (convoy.transition)")
            v = rows[name]
            if v.dtype.str != dtype or v.shape[lead:] != shape:
                raise ValueError(f"rows: {name!r} is {v.dtype.str} {v.shape[lead:]} per row; the declared "
                                 f"transition holds {dtype} {shape}")  # fmt: skip

    def _add_valid(self, rows: dict[str, np.ndarray], valid: np.ndarray) -> None:
        """A population's rows ``[R, M, …]`` where ``valid [R, M]``: run k's valid rows go to its ring in order, as
        ``add`` of just those rows writes a single run's (the newest ``capacity`` of them when there are more)."""
        valid = np.asarray(valid, dtype=bool)
        rows = {k: np.asarray(v) for k, v in rows.items()}
        if any(v.shape[:2] != valid.shape for v in rows.values()) or valid.shape[0] != self.runs:
            shapes = {k: v.shape[:2] for k, v in rows.items()}
            raise ValueError(f"rows: every field needs the leading shape of valid {valid.shape}, got {shapes}")
        if not self._data:
            self._data = {k: self._allocate(np.moveaxis(v, 0, 1)) for k, v in rows.items()}
        elif set(rows) != set(self._data):
            raise ValueError(f"rows: fields {sorted(rows)} differ from the buffer's {sorted(self._data)}")
        count = valid.sum(axis=1)
        self._room(int(np.minimum(self._next + count, self.capacity).max(initial=0)))
        skip = np.maximum(count - self.capacity, 0)  # only the newest rows can survive
        rank = np.cumsum(valid, axis=1) - 1 - skip[:, None]
        run, col = np.nonzero(valid & (rank >= 0))
        dest = (self._next[run] + rank[run, col]) % self.capacity
        for k, v in rows.items():
            self._data[k][run, dest] = v[run, col]
        self._next = (self._next + count - skip) % self.capacity
        self._size = np.minimum(self._size + count, self.capacity)

    def _allocate(self, v: np.ndarray, rows: int = 0) -> np.ndarray:
        """A zeroed field for rows like ``v``'s: ``reserve`` rows per run, or ``rows`` when more (≤ capacity)."""
        n = min(max(self._reserve, rows), self.capacity)
        if self.runs is None:
            return np.zeros((n, *v.shape[1:]), dtype=v.dtype)
        return np.zeros((v.shape[1], n, *v.shape[2:]), dtype=v.dtype)

    def sample(self, n: int, rng: np.random.Generator | list[np.random.Generator]) -> dict[str, np.ndarray]:
        """``n`` rows drawn uniformly with replacement; a population's ``[R, n, …]``, run k's rows drawn by
        ``rng[k]`` exactly as a single run's buffer would draw them."""
        if len(self) == 0:
            raise ValueError("sample() from an empty replay buffer")
        if self.runs is None:  # a single run is given its one stream, a population one per run
            idx = cast(np.random.Generator, rng).integers(0, int(self._size), size=n)
            return {k: v[idx] for k, v in self._data.items()}
        gens = cast(list[np.random.Generator], rng)
        idx = np.stack([g.integers(0, size, size=n) for g, size in zip(gens, self._size.tolist(), strict=True)])
        run = np.arange(self.runs)[:, None]
        return {k: v[run, idx] for k, v in self._data.items()}

    def state_dict(self) -> dict[str, Any]:
        """Contents for a full checkpoint (only the filled part; a population's up to its fullest run's size)."""
        top = int(self._size.max(initial=0))
        filled = np.s_[:top] if self.runs is None else np.s_[:, :top]
        return {"data": {k: v[filled].copy() for k, v in self._data.items()}, "next": self._next.copy(),
                "size": self._size.copy()}  # fmt: skip

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """What ``state_dict`` wrote (a file without ``size`` holds every run's rows up to its length)."""
        self._data = {}
        self._next = np.zeros(self.runs or (), dtype=np.int64)
        self._size = np.zeros(self.runs or (), dtype=np.int64)
        if not state["data"]:
            return
        data = {k: np.asarray(v) for k, v in state["data"].items()}
        first = next(iter(data.values()))
        rows = first.shape[0] if self.runs is None else first.shape[1]
        if rows > self.capacity:
            raise ValueError(f"replay: {rows} rows saved, more than the capacity {self.capacity}")
        self._data = {
            k: self._allocate(v if self.runs is None else np.moveaxis(v, 0, 1), rows) for k, v in data.items()
        }
        for k, v in data.items():
            self._data[k][np.s_[:rows] if self.runs is None else np.s_[:, :rows]] = v
        shape = self._size.shape
        self._size = np.broadcast_to(np.asarray(state.get("size", rows), dtype=np.int64), shape).copy()
        self._next = np.broadcast_to(np.asarray(state["next"], dtype=np.int64), shape) % self.capacity
