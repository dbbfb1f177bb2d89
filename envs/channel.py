"""A lossy radio for the agents' messages: packet drops, bit flips and one step of latency.

Messages belong to the learning algorithms, not to the env (the paper's env gives no reward for
them), so the channel is a separate object that evaluation puts between senders and receivers.
Messages are bit vectors ``[B, N, bits]`` (0/1); each receiver gets each other sender's message
independently: dropped with ``drop``, else with each bit flipped with ``flip``. A dropped message
arrives as zeros and ``delivered`` is False for it, so a model may substitute its own prediction
(the memory-module variants do). ``latency=1`` delivers what was sent on the previous step
(zeros on an episode's first step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from convoy.validation import build_config


class ChannelConfig(BaseModel):
    """Impairments of the broadcast channel."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    drop: float = Field(0.0, ge=0.0, le=1.0, description="Probability a message does not reach a receiver.")
    flip: float = Field(0.0, ge=0.0, le=1.0, description="Probability each delivered bit is inverted.")
    latency: int = Field(0, ge=0, le=1, description="Steps of delay: 0 (same step) or 1 (previous step's message).")


@dataclass(frozen=True)
class Received:
    """What every receiver heard from every sender this step."""

    bits: np.ndarray  # [B, N_receivers, N_senders, bits] float32 (0/1)
    delivered: np.ndarray  # [B, N_receivers, N_senders] bool; the diagonal (own message) is always True


class MessageChannel:
    """Applies ``ChannelConfig`` to batches of broadcast messages."""

    def __init__(self, config: ChannelConfig | None = None, seed: int | None = None) -> None:
        self.cfg = config or ChannelConfig()
        self._rng = np.random.default_rng(seed)
        self._pending: np.ndarray | None = None

    @classmethod
    def from_spec(cls, spec: str, seed: int | None = None) -> MessageChannel:
        """Parse ``"drop=0.3,flip=0.01,latency=1"`` (the CLI's ``--channel`` syntax)."""
        values: dict[str, float] = {}
        for part in filter(None, (p.strip() for p in spec.split(","))):
            key, sep, val = part.partition("=")
            if not sep:
                raise ValueError(f"channel: expected key=value pairs like 'drop=0.3,flip=0.01', got {part!r}")
            values[key.strip()] = float(val)
        return cls(build_config(ChannelConfig, **values), seed)

    def reset(self, envs: np.ndarray | None = None) -> None:
        """Forget in-flight messages (all envs, or those whose episode just ended)."""
        if self._pending is not None:
            if envs is None:
                self._pending = None
            else:
                self._pending[envs] = 0

    def _delay(self, msg: np.ndarray) -> np.ndarray:
        """With ``latency=1`` the previous call's messages (zeros at first, or when the layout changed)."""
        if not self.cfg.latency:
            return msg
        pending = self._pending
        sent = np.zeros_like(msg) if pending is None or pending.shape != msg.shape else pending
        self._pending = msg.copy()
        return sent

    def _impair(self, heard: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flip bits and drop whole messages of ``heard [..., bits]`` (modified in place): (bits, delivered)."""
        if self.cfg.flip > 0:
            flips = self._rng.random(heard.shape) < self.cfg.flip
            heard = np.where(flips, 1.0 - heard, heard).astype(np.float32)
        delivered = self._rng.random(heard.shape[:-1]) >= self.cfg.drop
        return heard, delivered

    def transmit(self, messages: np.ndarray) -> Received:
        """Send ``[B, N, bits]`` messages through the channel; returns what each receiver got."""
        msg = np.asarray(messages, dtype=np.float32)
        if msg.ndim != 3:
            raise ValueError(f"messages: expected shape [B, N, bits], got {msg.shape}")
        sent = self._delay(msg)
        b, n, bits = sent.shape
        heard, delivered = self._impair(np.broadcast_to(sent[:, None, :, :], (b, n, n, bits)).copy())
        own = np.eye(n, dtype=bool)
        delivered |= own
        heard[own[None].repeat(b, 0)] = np.broadcast_to(sent[:, :, :], (b, n, bits)).reshape(-1, bits)
        heard *= delivered[..., None]
        return Received(heard, delivered)

    def deliver(self, heard: np.ndarray) -> Received:
        """Impair messages already laid out per receiver and sender, ``[B, R, S, bits]``: each (receiver, sender)
        message is dropped or has its bits flipped independently (what a policy hears from its peers; the
        algorithms decide the layout, e.g. MA-BoN's one broadcast is S = 1)."""
        msg = np.asarray(heard, dtype=np.float32)
        if msg.ndim != 4:
            raise ValueError(f"heard: expected shape [B, receivers, senders, bits], got {msg.shape}")
        out, delivered = self._impair(self._delay(msg).copy())
        out *= delivered[..., None]
        return Received(out, delivered)
