"""Per-run random streams on the device: one batched draw for all R runs, run k's numbers a function of its seed and
its own counter alone.

Why counter-based. Run k of a population must draw exactly what the single run of seed k draws
(``tests/test_population.py``), and a draw for all runs must cost the same kernels at any R: a Python loop of one
``torch.Generator`` call per run grows with the population, and torch has no batched per-run generator. So every
number is a hash of (key, counter, index), the counter-based construction of Salmon et al. (2011), "Parallel random
numbers: as easy as 1, 2, 3": run k's key comes from its seed and the stream's purpose (``STREAMS``), its counter is a
device tensor that each draw advances in place (no host read, so a draw can be captured in a CUDA graph), and the
index is the element's place in the draw's per-run shape. ``envs.rng`` does the same for the envs, on the host.

Why this hash. Thomas Mueller's ``hash32`` (x ← ((x ≫ 16) ⊕ x) · 0x45d9f3b twice, then (x ≫ 16) ⊕ x;
https://stackoverflow.com/a/12996028) is a bijection of 32-bit words with good avalanche, and its multiplier is below
2^27: with values kept below 2^32 in int64 no product reaches 2^63, so it is plain int64 tensor arithmetic on any
device, without unsigned types or overflow. Philox-4x32 (Salmon et al.; torch's CUDA generator) multiplies 32-bit
words by 32-bit constants, which in signed int64 needs 16-bit limbs: several times the kernels per draw. A draw is

    s_k  = hash32(key_k ⊕ counter_k)                one word per run
    v_ki = hash32(hash32(i ⊕ SALT) ⊕ s_k)            one word per element

Each step is a bijection, so distinct counters give distinct s_k and a draw never repeats a word within a run; the
index is hashed before it meets s_k, so two draws are never shifted copies of each other. A word has 32 bits:
uniform floats take the top 24 (float32's mantissa), integers in [0, high) are ``(v · high) ≫ 32`` (Lemire's
multiply-shift, "Fast random integer generation in an interval", 2019; without rejection a value is off by at most
high / 2^32 relative: 2.4e-4 at 1 M replay rows), normals are Box–Muller over pairs of uniforms. The counter is used
modulo 2^32: a stream repeats after 2^32 draws, far more than any run makes (a few per update and per act).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import TypeVar

import torch
from torch import Tensor

M32 = 0xFFFFFFFF
MUL = 0x45D9F3B  # Mueller's multiplier: < 2^27, so a 32-bit word times it stays < 2^59
SALT = 0x9E3779B9  # 2^32 / golden ratio: hash32(0) = 0, so indices and purposes are salted first
STREAMS: tuple[str, ...] = ("replay", "explore", "noise")  # an agent's purposes, each its own stream per run

Word = TypeVar("Word", int, Tensor)


def hash32(x: Word) -> Word:
    """Mueller's ``hash32`` of words in [0, 2^32) (Python ints or int64 tensors): a bijection of 32-bit words."""
    x = ((x >> 16) ^ x) * MUL & M32
    x = ((x >> 16) ^ x) * MUL & M32
    return (x >> 16) ^ x


def run_key(seed: int, stream: str) -> int:
    """A run's key for one purpose: for a given purpose a bijection of seeds below 2^32 (distinct runs, distinct
    keys), higher bits of the seed folded in after."""
    s = int(seed) % (1 << 64)
    purpose = hash32((SALT + STREAMS.index(stream)) & M32)
    return hash32(hash32((s & M32) ^ purpose) ^ (s >> 32))


def legacy_counter(seed: int, updates: int) -> int:
    """Where the streams of a run restored from a checkpoint written before them (numpy and torch generator states)
    start: a function of its seed and update count, so every resume of that file draws the same numbers (not those
    the old generators would have drawn)."""
    return hash32(hash32(int(seed) % (1 << 64) & M32) ^ (int(updates) & M32))


@functools.lru_cache(maxsize=64)
def index_words(n: int, device: torch.device) -> Tensor:
    """``hash32(i ⊕ SALT)`` for i < n: the same for every draw of n numbers, so kept (a draw then costs one hash of
    its words and one of the runs' counters). Never written to."""
    return hash32(torch.arange(n, dtype=torch.int64, device=device) ^ SALT)


def to_uniform(words: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """Words → floats in [0, 1) of ``dtype``: as many top bits as its mantissa holds exactly (24 for float32)."""
    bits = min(1 - round(math.log2(torch.finfo(dtype).eps)), 32)  # float32: eps 2^-23, 24 bits
    return (words >> (32 - bits)).to(dtype) * 2.0**-bits


def to_integers(words: Tensor, high: Tensor | int) -> Tensor:
    """Words → integers in [0, high) by multiply-shift; ``high`` (< 2^31, broadcast against the words) may differ
    per run or per column."""
    return (words * high) >> 32


class RunStreams:
    """R streams of one purpose, one per run: every draw returns ``[R, *shape]`` from one batched computation and
    moves each run's counter on by one."""

    def __init__(self, seeds: Sequence[int], stream: str, device: str | torch.device = "cpu") -> None:
        self.seeds, self.stream = tuple(int(s) for s in seeds), stream
        self.keys = torch.tensor([run_key(s, stream) for s in self.seeds], dtype=torch.int64, device=device)
        self.counters = torch.zeros(len(self.seeds), dtype=torch.int64, device=device)  # [R], advanced in place

    @property
    def runs(self) -> int:
        return len(self.seeds)

    def bits(self, shape: Sequence[int] | int, advance: Tensor | None = None) -> Tensor:
        """``[R, *shape]`` words in [0, 2^32) (int64). ``advance`` ``[R]`` (0/1) moves only those runs' counters:
        a run that uses none of this draw keeps its stream where it was."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        per_run = hash32(self.keys ^ (self.counters & M32))  # [R]
        # a captured update traces the hash instead (dynamo ignores the cache and warns that it does)
        index = index_words.__wrapped__ if torch.compiler.is_compiling() else index_words
        words = hash32(index(math.prod(shape), self.keys.device) ^ per_run[:, None])
        self.counters.add_(1 if advance is None else advance)
        return words.view(self.runs, *shape)

    def uniform(self, shape: Sequence[int] | int, dtype: torch.dtype = torch.float32) -> Tensor:
        """``[R, *shape]`` floats in [0, 1)."""
        return to_uniform(self.bits(shape), dtype)

    def integers(self, high: Tensor | int, shape: Sequence[int] | int) -> Tensor:
        """``[R, *shape]`` integers in [0, high) (``high`` broadcast against them: ``[R, 1]`` one per run)."""
        return to_integers(self.bits(shape), high)

    def normal(self, shape: Sequence[int] | int, dtype: torch.dtype = torch.float32) -> Tensor:
        """``[R, *shape]`` standard normals: Box–Muller, both of each pair's outputs used."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        n = math.prod(shape)
        work = torch.float64 if dtype == torch.float64 else torch.float32
        words = self.bits((2, (n + 1) // 2))
        radius = torch.sqrt(-2.0 * torch.log(1.0 - to_uniform(words[:, 0], work)))  # 1 − u ∈ (0, 1]
        angle = (2.0 * math.pi) * to_uniform(words[:, 1], work)
        z = torch.cat([radius * torch.cos(angle), radius * torch.sin(angle)], dim=1)[:, :n]
        return z.reshape(self.runs, *shape).to(dtype)

    def state(self, run: int) -> int:
        """Run ``run``'s counter (what a checkpoint keeps, with the run's seed)."""
        return int(self.counters[run])

    def load(self, run: int, counter: int, seed: int | None = None) -> None:
        """Put run ``run`` at ``counter``, of the stream of ``seed`` when given (a state saved by another seed's
        run goes on as that run)."""
        if seed is not None and int(seed) != self.seeds[run]:
            self.seeds = (*self.seeds[:run], int(seed), *self.seeds[run + 1 :])
            self.keys[run] = run_key(int(seed), self.stream)
        self.counters[run] = int(counter)
