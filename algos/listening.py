"""What agents hear at execution: the true messages, a lossy channel, the memory module's predictions, or noise.

Training always uses the true messages (centralised training). Evaluation may put something else between the
message networks and the policy networks, which is how the paper probes its models (section 6.3: white noise in
place of messages; section 6.4: no channel at all, the memory module's prediction instead). Every algorithm whose
messages are discrete bits (MA-MeSN, MA-BoN and their ``-mm`` variants) exposes what each receiver hears as
``[B, receivers, senders, bits]`` — MA-MeSN: the N − 1 peers; MA-BoN: its one broadcast — and passes it through
``Listening.hear`` before the policy network reads it.

* ``sent``: the true messages, through ``channel`` when one is set (``envs.channel``: drops, bit flips, latency).
  A dropped message arrives as zeros — or, for a memory-module algorithm, as the module's prediction: that is the
  "mix" of true and predicted messages when the channel loses packets.
* ``predicted``: no channel at all; every message is the memory module's prediction (fully decentralised).
* ``noise``: uniformly random bits in place of every message (Table 1's "reward with white noise"). Out of
  distribution: a listener may fail on bits no speaker ever sends, whether or not it uses what they say.
* ``shuffled``: each env hears the messages sent in another env at the same step (a random derangement of the
  envs each step): real messages, their content unrelated to this env. In distribution.
* ``modal``: every receiver hears each sender's most frequent message so far in the evaluation: a real, constant
  message that carries nothing. In distribution.

* ``fixed``: every receiver hears all-zero bits: the constant a cut channel delivers (what a model trained with its
  channel cut hears), whether or not any speaker sends it.

"Listeners use the messages" means true messages beat ``shuffled`` and ``modal``, not only ``noise``.

``fill_lost="zeros"`` makes a memory-module algorithm hear zeros for lost messages, like a plain MA-MeSN/MA-BoN: the
same trained policy with and without its memory, for the channel-robustness comparison.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Literal, get_args

import numpy as np
import torch
from torch import Tensor, nn

from convoy.config import MessageSource
from convoy.envs.channel import MessageChannel
from convoy.validation import ConfigError

if TYPE_CHECKING:  # the mixin sits on a NetworkAgent: the checker reads it as one, at run time it is a plain class
    from convoy.algos.algorithm import NetworkAgent as _OnAgent
    from convoy.config import BoNConfig, MeSNConfig
else:
    _OnAgent = object

Source = MessageSource
SOURCES: tuple[str, ...] = get_args(Source)


class Listening:
    """Turns the true messages (and, for memory modules, their predictions) into what the policies hear."""

    def __init__(
        self,
        source: Source = "sent",
        channel: MessageChannel | None = None,
        seed: int | None = None,
        fill_lost: Literal["predicted", "zeros"] = "predicted",
    ) -> None:
        if source not in SOURCES:
            raise ConfigError("messages", f"unknown source {source!r}; choose one of: {', '.join(SOURCES)}")
        if channel is not None and source != "sent":
            raise ConfigError("channel", f"a channel carries true messages; it does not apply to messages={source}")
        self.source, self.channel, self.fill_lost = source, channel, fill_lost
        self._gen = torch.Generator().manual_seed(int(np.random.SeedSequence(seed).generate_state(1)[0]))
        self._counts: dict[tuple[int, int, int], int] = {}  # (receiver, sender, message code) → times sent
        self._modes: dict[tuple[int, int], int] = {}  # (receiver, sender) → its most frequent code so far

    @property
    def needs_prediction(self) -> bool:
        """Whether a memory-module algorithm must run its module this step (predictions replace lost messages)."""
        return self.source == "predicted" or (self.channel is not None and self.fill_lost == "predicted")

    def hear(self, true: Tensor, predicted: Tensor | None = None) -> Tensor:
        """What every receiver hears, ``[B, R, S, bits]`` in 0/1, from the true messages of the same layout."""
        if self.source == "noise":
            return torch.randint(0, 2, true.shape, generator=self._gen).to(true)
        if self.source == "shuffled":
            return true[self._derangement(true.shape[0]).to(true.device)]
        if self.source == "modal":
            return self._modal(true)
        if self.source == "fixed":
            return torch.zeros_like(true)
        if self.source == "predicted":
            if predicted is None:
                raise ConfigError(
                    "messages", "'predicted' needs a memory-module algorithm (ma-mesn-mm, ma-bon-mm); use sent or noise"
                )
            return predicted
        if self.channel is None:
            return true
        got = self.channel.deliver(true.detach().cpu().numpy())
        heard = torch.as_tensor(got.bits, device=true.device, dtype=true.dtype)
        if predicted is None:
            return heard  # lost messages stay zeros
        delivered = torch.as_tensor(got.delivered, device=true.device).unsqueeze(-1)
        return torch.where(delivered, heard, predicted)

    def _derangement(self, n: int) -> Tensor:
        """A random permutation of ``n`` envs with no env mapped to itself (a random cycle through all of them)."""
        if n < 2:
            raise ConfigError("messages", "shuffled messages need at least 2 envs evaluated together")
        order = torch.randperm(n, generator=self._gen)
        perm = torch.empty_like(order)
        perm[order] = order.roll(-1)
        return perm

    def _modal(self, true: Tensor) -> Tensor:
        """Each sender's most frequent message so far (counted per receiver, this step's included), for every env."""
        bits = true.shape[-1]
        if bits > 62:
            raise ConfigError("messages", f"modal messages are counted as integers: at most 62 bits (got {bits})")
        weights = 2 ** torch.arange(bits, device=true.device, dtype=torch.int64)
        codes = (true.round().long() * weights).sum(-1).cpu()  # [B, receivers, senders]
        b, receivers, senders = codes.shape
        pair = torch.stack(torch.meshgrid(torch.arange(receivers), torch.arange(senders), indexing="ij"), -1)
        triples, counts = torch.unique(torch.cat([pair.expand(b, -1, -1, -1), codes.unsqueeze(-1)], -1).reshape(-1, 3),
                                       dim=0, return_counts=True)  # fmt: skip
        for (r, s, v), c in zip(triples.tolist(), counts.tolist(), strict=True):
            n = self._counts[r, s, v] = self._counts.get((r, s, v), 0) + c
            best = self._modes.get((r, s))  # counts only grow: the mode is the old one or a message seen this step
            if best is None or (n, -v) > (self._counts[r, s, best], -best):
                self._modes[r, s] = v
        modal = torch.tensor([[self._modes[r, s] for s in range(senders)] for r in range(receivers)])
        heard = (modal.unsqueeze(-1) >> torch.arange(bits)) & 1  # [receivers, senders, bits]
        return heard.to(true).expand_as(true).clone()

    def reset(self, done: np.ndarray) -> None:
        """Forget in-flight messages of envs whose episode ended (channel latency)."""
        if self.channel is not None and done.any():
            self.channel.reset(np.flatnonzero(done))


class HearsMessages(_OnAgent):
    """Mixin for algorithms whose policies read discrete messages laid out ``[..., N, senders·bits]``.

    The algorithm provides ``speak`` (observations → id-augmented inputs, messages sent, messages heard) and
    ``listen`` (inputs + heard → Q-values); ``hear`` applies the evaluation's ``listening`` (None in training and
    by default: the true messages, untouched).
    """

    listening: Listening | None = None
    senders: int  # messages each agent hears per step (MA-MeSN: N − 1 peers, MA-BoN: 1 broadcast)
    cfg: MeSNConfig | BoNConfig  # a config with ``channel_control``
    bits: int

    def reset_runs(self, state: Any, done: np.ndarray) -> Any:
        """Also forget the channel's in-flight messages of envs whose episode ended (latency; evaluation's single
        run, ``done [1, B]``)."""
        if self.listening is not None:
            self.listening.reset(done.reshape(-1))
        return super().reset_runs(state, done)

    def control(self, heard: Tensor) -> Tensor:
        """What listeners hear under ``channel_control`` (in training and at execution): the messages, zeros
        (the channel cut) or fresh uniform bits from each run's own generator."""
        how = self.cfg.channel_control
        if how == "cut":
            return torch.zeros_like(heard)
        if how == "noise":
            return (self.rand_like(heard) < 0.5).to(heard.dtype)
        return heard

    def message_logits(self, nets: nn.ModuleDict, obs: Tensor) -> Tensor:
        """Every sender's message logits ``[..., senders, 2·bits]`` from the raw observations ``[..., N, D]``."""
        raise NotImplementedError

    def hear(self, heard: Tensor, predicted: Tensor | None = None) -> Tensor:
        if self.listening is None:
            return heard
        shape = heard.shape  # [R, B, N, senders·bits]: a listening serves one run (evaluation), as envs [R·B]
        split = (-1, shape[-2], self.senders, self.bits)
        pred = None if predicted is None else predicted.reshape(split)
        return self.listening.hear(heard.reshape(split), pred).reshape(shape)
