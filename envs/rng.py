"""Counter-based random numbers: every draw is a pure function of (env key, tick, stream, index).

A batch of B envs must evolve bit-for-bit like the same B envs stepped one at a time. A shared
``np.random.Generator`` cannot give that (the order of draws would depend on the batch), and B
generators would need a Python loop per step. Hashing the counters with SplitMix64 is
vectorised, batch-independent and fast.
"""

from __future__ import annotations

from typing import cast

import numpy as np

from convoy.envs.batched import env_seeds

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_TICK_MUL = np.uint64(0x632BE59BD9B4E019)
_STREAM_MUL = np.uint64(0x8CB92BA72F3D8DD7)
_S30, _S27, _S31, _S11 = (np.uint64(s) for s in (30, 27, 31, 11))
_INV_2_53 = 1.0 / (1 << 53)

# Named streams, so that two purposes never share draws.
STREAM_ADVERSARY = 1
STREAM_SPAWN = 2
STREAM_TARGET = 3
STREAM_ENTER = 4


def splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser on a uint64 array (wrapping arithmetic is intended)."""
    z = x + _GOLDEN
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


def env_keys(seeds: np.ndarray) -> np.ndarray:
    """One 64-bit key per env from its integer seed."""
    return splitmix64(np.asarray(seeds).astype(np.uint64))


def _columns(stream: int, n: int) -> np.ndarray:
    """The counter offsets of a stream's first ``n`` columns (uint64, wrapping)."""
    return np.uint64((stream * int(_STREAM_MUL)) & 0xFFFFFFFFFFFFFFFF) + np.arange(n, dtype=np.uint64)


def _draw(keys: np.ndarray, ticks: np.ndarray, columns: np.ndarray) -> np.ndarray:
    counter = ticks.astype(np.uint64)[:, None] * _TICK_MUL + columns[None, :]
    bits = splitmix64(keys[:, None] ^ splitmix64(counter))
    return (bits >> _S11).astype(np.float64) * _INV_2_53


def uniform(keys: np.ndarray, ticks: np.ndarray, stream: int, n: int) -> np.ndarray:
    """``[len(keys), n]`` floats in [0, 1), a function of (key_b, tick_b, stream, column) only."""
    return _draw(keys, ticks, _columns(stream, n))


def uniforms(keys: np.ndarray, ticks: np.ndarray, *draws: tuple[int, int]) -> list[np.ndarray]:
    """``uniform(keys, ticks, stream, n)`` for each ``(stream, n)`` of ``draws``, hashed in one pass: a step's
    draws cost one call's overhead instead of one per purpose (the values are the same)."""
    sizes = [n for _, n in draws]
    table = _draw(keys, ticks, np.concatenate([_columns(stream, n) for stream, n in draws]))
    return np.split(table, np.cumsum(sizes)[:-1], axis=1)


class EnvStreams:
    """One counter-based stream per env: a key from its seed and a tick that advances once per step.

    The one place that turns a reset's ``seed`` into per-env streams, so every batched env seeds alike:
    an int is expanded by ``envs.batched.env_seeds``, an array gives each env its seed, None keeps the
    current streams (fresh OS entropy the very first time).
    """

    def __init__(self, num_envs: int) -> None:
        self.keys = np.zeros(num_envs, np.uint64)
        self.ticks = np.zeros(num_envs, np.uint64)
        self._seeded = False

    def seed(self, seed: int | np.ndarray | None) -> None:
        if seed is None and not self._seeded:
            seed = cast(int, np.random.SeedSequence().entropy) % (1 << 62)  # fresh OS entropy: an int
        if seed is not None:
            self.keys = env_keys(env_seeds(seed, len(self.keys)))
            self.ticks[:] = 0
            self._seeded = True

    def advance(self) -> None:
        """Move every env to its next tick (once per step), so the next draws are fresh."""
        self.ticks += np.uint64(1)

    def uniform(self, stream: int, n: int, envs: np.ndarray | None = None) -> np.ndarray:
        """``[B, n]`` (or ``[len(envs), n]``) floats in [0, 1) from the current tick."""
        if envs is None:
            return uniform(self.keys, self.ticks, stream, n)
        return uniform(self.keys[envs], self.ticks[envs], stream, n)

    def uniforms(self, *draws: tuple[int, int], envs: np.ndarray | None = None) -> list[np.ndarray]:
        """``uniform(stream, n, envs)`` for each ``(stream, n)`` of ``draws``, in one pass."""
        if envs is None:
            return uniforms(self.keys, self.ticks, *draws)
        return uniforms(self.keys[envs], self.ticks[envs], *draws)
