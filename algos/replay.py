"""The joint replay buffer: a preallocated ring of whole joint transitions, held on the training device.

Centralized algorithms need every agent's view of the same step, so one row holds all agents' observations at t
and t+1, their actions and rewards, the termination flag and the episode id (what stabilised experience replay
weighs by), plus whatever else an algorithm asked to keep (a fingerprint, received messages). Rows are written
and read as whole slices, never one element at a time; tensors are allocated on the first insert, from its
shapes and dtypes, and never grow past ``capacity``. Given the declared transition (``convoy.transition.schema``),
every insert is held to it: a declared field of another dtype or shape is refused with its name.

``capacity`` is where the ring wraps; the tensors hold only the rows a run can store, ``reserve(rows)``: a run of
S env steps never stores more than about S rows, so a 20 k-step run with the treadmill's 1 M capacity allocates
20 k rows, not 1 M (1.2 GB). Should more come (a resumed run past its budget), the tensors grow, up to ``capacity``.
Until a ring wraps its rows sit at 0 … size − 1 whatever its allocation, and samples draw ``[0, size)``: a run
that fits reads and samples exactly what it did with every row allocated up front.

R runs (a single run is R = 1) keep R rings in one tensor ``[R, rows, …]``, each with its own write pointer and
size: usually every run inserts the same rows at the same times, but a hierarchical meta-controller gets a
transition only where an option ended, so ``add(rows, valid)`` inserts each run's valid rows only.

Why on the device. An update samples a batch: drawn on the host, that was one generator call per run and a copy of
every field to the device, every update. Here the rows live where the networks train (``device``), inserts copy the
host's numpy chunks over once (on CUDA through pinned memory, without blocking), and ``sample`` draws every run's
indices in one batched draw of the runs' own streams (``algos.streams``), over each run's own rows, and gathers
device tensors: run k's batch is exactly what the single run of its seed samples. The write pointers and sizes stay
on the host, where the inserts come from; the sizes are mirrored on the device, so a sample reads no host value.
``state_dict`` writes numpy arrays, the layout the replay files (``replay.npz``) have always had.

Prioritized replay (``prioritized``; Schaul et al. 2016, "Prioritized experience replay"). Each row holds a priority
(the agent's ``(|δ| + ε)^α``; a new row the largest any row of its run has had, so it is drawn soon), and
``sample_prioritized`` draws row i with probability p_i / Σp, stratified (one draw from each of n equal slices of
the mass), with importance weights (N · P(i))^−β over their batch's largest. The priorities are two levels, rows
and the sums of blocks of ``BLOCK`` rows, both on the device: a draw picks a block by the block sums' cumulative
sum, then a row by the block's; an update of n rows' priorities re-sums only their blocks, exactly (no running
sums that drift). At a million rows and three runs that is ~2 ms a batch on one CPU core where a cumulative sum
over all rows is ~20 ms (measured side by side); Schaul et al.'s sum tree is a pointer structure a batched device
draw cannot walk cheaply.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from convoy.algos.streams import RunStreams
from convoy.transition import TRANSITION, Transition, from_columns

BLOCK = 1024  # rows per block of prioritized replay's two-level sums


def torch_dtype(dtype: np.dtype[Any]) -> torch.dtype:
    """The torch dtype of a numpy one."""
    return torch.from_numpy(np.empty(0, dtype)).dtype


class JointReplay:
    """Fixed-capacity ring of transitions; ``add`` takes numpy rows, ``sample`` returns device tensors. The rows are
    kept as one tensor per field (the declared ones and the algorithm's extras alike), by name."""

    def __init__(
        self,
        capacity: int,
        runs: int = 1,
        declared: dict[str, tuple[str, tuple[int, ...]]] | None = None,
        device: str | torch.device = "cpu",
        prioritized: bool = False,
    ) -> None:
        if not 1 <= capacity < 2**31:  # sample's multiply-shift needs size · 2^32 < 2^63
            raise ValueError(f"capacity: must be ≥ 1 and < 2^31 (got {capacity})")
        self.capacity = capacity
        self.runs = runs
        self.declared = declared or {}  # field → (dtype, per-row shape) every insert must hold
        self.device = torch.device(device)
        self._data: dict[str, Tensor] = {}  # field → [R, rows, …]
        self._reserve = capacity  # rows allocated at the first insert (``reserve``)
        self._next = np.zeros(runs, dtype=np.int64)  # per run [R]
        self._size = np.zeros(runs, dtype=np.int64)
        self._high = torch.zeros(runs, 1, dtype=torch.int64, device=self.device)  # the sizes, on the device
        self._run = torch.arange(runs, device=self.device)[:, None]  # [R, 1]: where each run's rows start
        self.prioritized = prioritized
        self._priority = torch.zeros(runs, 0, device=self.device)  # [R, blocks · BLOCK]: 0 where no row is
        self._block_sum = torch.zeros(runs, 0, device=self.device)  # [R, blocks]
        self._max_priority = torch.ones(runs, 1, device=self.device)  # what a new row of each run gets

    def __len__(self) -> int:
        """Rows held (the fewest any run holds)."""
        return int(self._size.min())

    @property
    def nbytes(self) -> int:
        """Bytes allocated (all runs')."""
        return sum(v.numel() * v.element_size() for v in self._data.values())

    @property
    def allocated(self) -> int:
        """Rows allocated per run: ``capacity`` once the ring has wrapped, up to then as few as ``reserve`` asked."""
        if not self._data:
            return 0
        return int(next(iter(self._data.values())).shape[1])

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
            new = torch.zeros((v.shape[0], rows, *v.shape[2:]), dtype=v.dtype, device=v.device)
            new[:, :held] = v
            self._data[k] = new
        self._fit_priorities()

    def add(self, rows: Transition[np.ndarray], valid: np.ndarray | None = None) -> None:
        """Append rows ``[R, M, …]`` (every array shares the leading dims); the oldest rows are overwritten when full.
        ``valid [R, M]``: only those rows, each run's in order, to its ring."""
        self.add_columns(rows.columns(), valid)

    def add_columns(self, columns: dict[str, np.ndarray], valid: np.ndarray | None = None) -> None:
        """``add`` of the fields by name: for a buffer of other rows than transitions (demonstrations)."""
        runs = {k: np.asarray(v) for k, v in columns.items()}
        if any(v.ndim < 2 or v.shape[0] != self.runs for v in runs.values()):
            shapes = {k: v.shape for k, v in runs.items()}
            raise ValueError(f"rows: every field needs the leading shape [R = {self.runs}, M], got {shapes}")
        self._check_declared(runs)
        if valid is not None or (self._next != self._next[0]).any():
            ones = np.ones(np.shape(next(iter(runs.values())))[:2], bool)
            self._add_valid(runs, ones if valid is None else np.asarray(valid, bool).reshape(len(self._next), -1))
            return
        sizes = {k: v.shape[1] for k, v in runs.items()}
        m = next(iter(sizes.values()))
        if any(s != m for s in sizes.values()):
            raise ValueError(f"rows: every field needs the same leading size, got {sizes}")
        self._fields(runs)
        if m > self.capacity:  # only the newest rows can survive
            runs = {k: v[:, -self.capacity :] for k, v in runs.items()}
            m = self.capacity
        at = int(self._next[0])  # one pointer for all runs here
        self._room(min(at + m, self.capacity))
        first = min(m, self.capacity - at)  # up to the end of the ring, then the wrapped rest: 2 slices
        for k, v in runs.items():
            staged = self._stage(v)
            self._data[k][:, at : at + first] = staged[:, :first]
            self._data[k][:, : m - first] = staged[:, first:]
        if self.prioritized:
            self._priority[:, at : at + first] = self._max_priority
            self._priority[:, : m - first] = self._max_priority
            self._sum_blocks()
        self._next = (self._next + m) % self.capacity
        self._size = np.minimum(self._size + m, self.capacity)
        self._sync_sizes()

    def _check_declared(self, rows: dict[str, np.ndarray]) -> None:
        for name, (dtype, shape) in self.declared.items():
            v = rows[name]
            if v.dtype.str != dtype or v.shape[2:] != shape:
                raise ValueError(f"rows: {name!r} is {v.dtype.str} {v.shape[2:]} per row; the declared "
                                 f"transition holds {dtype} {shape}")  # fmt: skip

    def _fields(self, runs: dict[str, np.ndarray]) -> None:
        """Allocate the fields from the first rows ``[R, M, …]``; later rows must bring the same fields."""
        if not self._data:
            self._data = {k: self._allocate(v) for k, v in runs.items()}
            self._fit_priorities()
        elif set(runs) != set(self._data):
            raise ValueError(f"rows: fields {sorted(runs)} differ from the buffer's {sorted(self._data)}")

    def _add_valid(self, runs: dict[str, np.ndarray], valid: np.ndarray) -> None:
        """Rows ``[R, M, …]`` where ``valid [R, M]``: run k's valid rows go to its ring in order, as ``add`` of
        just those rows writes a single run's (the newest ``capacity`` of them when there are more)."""
        if any(v.shape[:2] != valid.shape for v in runs.values()) or valid.shape[0] != len(self._next):
            shapes = {k: v.shape[:2] for k, v in runs.items()}
            raise ValueError(f"rows: every field needs the leading shape of valid {valid.shape}, got {shapes}")
        self._fields(runs)
        count = valid.sum(axis=1)
        self._room(int(np.minimum(self._next + count, self.capacity).max(initial=0)))
        skip = np.maximum(count - self.capacity, 0)  # only the newest rows can survive
        rank = np.cumsum(valid, axis=1) - 1 - skip[:, None]
        run, col = np.nonzero(valid & (rank >= 0))
        dest = (self._next[run] + rank[run, col]) % self.capacity
        at = (self._stage(run), self._stage(dest))
        for k, v in runs.items():
            self._data[k][at] = self._stage(v[run, col])  # only the kept rows cross to the device
        if self.prioritized:
            self._priority[at] = self._max_priority[at[0], 0]
            self._sum_blocks()
        self._next = (self._next + count - skip) % self.capacity
        self._size = np.minimum(self._size + count, self.capacity)
        self._sync_sizes()

    def _stage(self, v: np.ndarray) -> Tensor:
        """Host rows on the device. On CUDA through pinned memory and a non-blocking copy: the caching host allocator
        keeps the pinned block until its copy has run, so the next insert never overwrites rows in flight."""
        if self.device.type != "cuda":
            return torch.from_numpy(np.require(v, requirements=["C", "W"]))  # written into the ring, never kept
        pinned = torch.empty(v.shape, dtype=torch_dtype(v.dtype), pin_memory=True)
        pinned.numpy()[...] = v
        return pinned.to(self.device, non_blocking=True)

    def _sync_sizes(self) -> None:
        """The sizes onto the device after an insert, so that ``sample`` never reads them from the host."""
        self._high.copy_(torch.from_numpy(self._size).view(-1, 1))

    def _allocate(self, v: np.ndarray, rows: int = 0) -> Tensor:
        """A zeroed field for rows like ``v``'s ``[R, M, …]``: ``reserve`` rows per run, or ``rows`` when more (≤
        capacity)."""
        n = min(max(self._reserve, rows), self.capacity)
        return torch.zeros((v.shape[0], n, *v.shape[2:]), dtype=torch_dtype(v.dtype), device=self.device)

    def sample(self, n: int, streams: RunStreams) -> Transition[Tensor]:
        """``n`` rows per run drawn uniformly with replacement, on the device, ``[R, n, …]``: run k's rows drawn by its
        stream in ``streams`` (one batched draw for all runs) exactly as its single run's buffer would draw them."""
        return from_columns(self.sample_columns(n, streams))

    def sample_columns(self, n: int, streams: RunStreams) -> dict[str, Tensor]:
        """``sample`` as the fields held, by name: for a buffer of other rows than transitions (demonstrations)."""
        if len(self) == 0:
            raise ValueError("sample() from an empty replay buffer")
        if streams.runs != len(self._next):
            raise ValueError(f"streams: one per run ({len(self._next)}), got {streams.runs}")
        return self._gather(streams.integers(self._high, n), n)  # [R, n], run k's in [0, size_k)

    def _gather(self, idx: Tensor, n: int) -> dict[str, Tensor]:
        """Rows ``idx [R, n]`` of each run's ring, every field as a batch ``[R, n, …]``."""
        flat = idx.add(self._run, alpha=self.allocated).flatten()  # rows of the runs laid end to end
        return {k: v.flatten(0, 1).index_select(0, flat).view(-1, n, *v.shape[2:]) for k, v in self._data.items()}

    def sample_prioritized(self, n: int, streams: RunStreams, beta: float) -> tuple[Transition[Tensor], Tensor, Tensor]:
        """``n`` rows per run drawn in proportion to their priorities (prioritized replay), on the device: the batch
        ``[R, n, …]``, the rows drawn ``[R, n]`` (for ``set_priorities``) and their importance weights
        ``(size · P(i))^−β`` over the batch's largest, ``[R, n]``. One uniform draw of each run's stream."""
        if not self.prioritized:
            raise ValueError("sample_prioritized: this replay keeps no priorities (prioritized=False)")
        if len(self) == 0:
            raise ValueError("sample() from an empty replay buffer")
        u = streams.uniform(n)  # [R, n]
        strata = torch.arange(n, device=self.device, dtype=u.dtype)
        cum_blocks = torch.cumsum(self._block_sum, dim=1)  # [R, blocks]
        total = cum_blocks[:, -1:]
        mass = (strata + u) / n * total  # one point in each of n equal slices of the run's mass
        last = self._block_sum.shape[1] - 1
        block = torch.searchsorted(cum_blocks, mass, right=True).clamp_max(last)  # [R, n]
        rest = mass - (cum_blocks.gather(1, block) - self._block_sum.gather(1, block))
        within = torch.searchsorted(self._block_rows(block).cumsum(dim=2), rest[..., None], right=True).squeeze(-1)
        idx = torch.minimum(block * BLOCK + within.clamp_max(BLOCK - 1), self._high - 1)
        p = self._priority.gather(1, idx) / total
        weight = (self._high * p).pow(-beta)
        weight = weight / weight.amax(dim=1, keepdim=True)
        return from_columns(self._gather(idx, n)), idx, weight

    def set_priorities(self, idx: Tensor, priority: Tensor) -> None:
        """Rows ``idx [R, n]`` (drawn by ``sample_prioritized``) get ``priority [R, n]`` (> 0); a non-finite one
        (a run whose update was skipped) leaves its row's as it was. Only their blocks are re-summed."""
        old = self._priority.gather(1, idx)
        new = torch.where(torch.isfinite(priority), priority.to(old.dtype), old)
        self._priority.scatter_(1, idx, new)
        torch.maximum(self._max_priority, new.amax(dim=1, keepdim=True), out=self._max_priority)
        block = idx // BLOCK
        self._block_sum.scatter_(1, block, self._block_rows(block).sum(dim=2))

    def _block_rows(self, block: Tensor) -> Tensor:
        """The priorities of blocks ``block [R, n]``, ``[R, n, BLOCK]``."""
        return self._priority.view(self.runs, -1, BLOCK).gather(1, block[..., None].expand(-1, -1, BLOCK))

    def _fit_priorities(self) -> None:
        """Priorities for every allocated row, padded to whole blocks (the padding is never drawn: priority 0)."""
        if not self.prioritized:
            return
        rows = -(-self.allocated // BLOCK) * BLOCK
        held = self._priority.shape[1]
        if rows > held:
            new = torch.zeros(self.runs, rows, device=self.device)
            new[:, :held] = self._priority
            self._priority = new
            self._sum_blocks()

    def _sum_blocks(self) -> None:
        self._block_sum = self._priority.view(self.runs, -1, BLOCK).sum(dim=2)

    def state_dict(self) -> dict[str, Any]:
        """Contents for a full checkpoint, as numpy arrays ``[R, rows, …]`` (only the filled part: up to the fullest
        run's size)."""
        top = int(self._size.max(initial=0))
        data = {k: _host(v[:, :top]) for k, v in self._data.items()}
        state = {"data": data, "next": self._next.copy(), "size": self._size.copy()}
        if self.prioritized:
            state.update(priority=_host(self._priority[:, :top]), max_priority=_host(self._max_priority))
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """What ``state_dict`` wrote (a file without ``size`` holds every run's rows up to its length). A single run's
        file written before the run axis (rows ``[rows, …]``, 0-dim ``next`` and ``size``) loads as run 0's."""
        self._data = {}
        self._next = np.zeros(len(self._next), dtype=np.int64)
        self._size = np.zeros(len(self._next), dtype=np.int64)
        if state["data"]:
            data = {k: np.asarray(v) for k, v in state["data"].items()}
            if np.ndim(state["next"]) == 0:  # a single run's file from before the run axis
                data = {k: v[None] for k, v in data.items()}
            if "valid" in data:  # DIAL's sequences [R, S, L] from before they held every field: ``episode`` unread
                data.update({k: np.zeros(data["valid"].shape, TRANSITION[k].dtype) for k in TRANSITION.keys() - data})
            rows = next(iter(data.values())).shape[1]
            if rows > self.capacity:
                raise ValueError(f"replay: {rows} rows saved, more than the capacity {self.capacity}")
            self._data = {k: self._allocate(v, rows) for k, v in data.items()}
            for k, v in data.items():
                self._data[k][:, :rows] = self._stage(v)
            shape = self._size.shape
            self._size = np.broadcast_to(np.asarray(state.get("size", rows), dtype=np.int64), shape).copy()
            self._next = np.broadcast_to(np.asarray(state["next"], dtype=np.int64), shape) % self.capacity
        self._load_priorities(state)
        self._sync_sizes()

    def _load_priorities(self, state: dict[str, Any]) -> None:
        """The saved priorities, or (a file written without them) 1 for every row held: uniform until updated."""
        if not self.prioritized:
            return
        self._priority = torch.zeros(self.runs, 0, device=self.device)
        self._fit_priorities()
        if "priority" in state:
            saved, top = np.asarray(state["priority"], np.float32), np.asarray(state["max_priority"], np.float32)
            if saved.shape != (self.runs, int(self._size.max(initial=0))) or top.size != self.runs:
                raise ValueError(f"replay: priorities {saved.shape} (largest {top.shape}) do not fit its rows "
                                 f"{(self.runs, int(self._size.max(initial=0)))}")  # fmt: skip
            if not (np.isfinite(saved).all() and (saved >= 0).all() and np.isfinite(top).all() and (top > 0).all()):
                raise ValueError("replay: priorities must be finite and ≥ 0 (the largest > 0)")
            self._priority[:, : saved.shape[1]] = torch.as_tensor(saved, device=self.device)
            self._max_priority.copy_(torch.as_tensor(top).reshape(-1, 1))
        else:
            sizes = torch.as_tensor(self._size, device=self.device)[:, None]
            held = torch.arange(self._priority.shape[1], device=self.device) < sizes
            self._priority[held] = 1.0
            self._max_priority.fill_(1.0)
        self._sum_blocks()


def _host(t: Tensor) -> np.ndarray:
    """A numpy copy of ``t`` (one copy from a device, a copy of the rows on the CPU)."""
    host = t.detach().cpu()
    return host.numpy().copy() if host.data_ptr() == t.data_ptr() else host.numpy()
