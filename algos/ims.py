"""IMS (Iterative Message Sharing) = CommNet (Sukhbaatar et al. 2016), the paper's iterative-communication baseline.

Every agent encodes its observation into a hidden state ``h⁰_i``. Then, P = ``comm_iterations`` times, every agent
emits a message from its current hidden state, hears the *mean* of the other agents' messages
``c_i = mean_{j≠i} m_j`` and updates ``h^{p+1}_i = relu(W_h h^p_i + W_c c_i + h⁰_i)`` (CommNet's skip connection
from the encoding). The Q-values are a linear head on ``h^P_i``. One network therefore produces both the messages
and the behaviour, which is the coupling the paper blames for IMS's weaker results (section 6.1).

Choices made where the paper and CommNet leave room:

* Messages are ``message_bits`` discrete bits by default (Gumbel-softmax straight-through in training, argmax at
  execution), because the paper caps every message at 2 bytes. ``discrete=False`` gives CommNet's original
  continuous communication: the message is then a linear map of ``h^p`` to ``message_bits`` real values (CommNet
  sends ``h^p`` itself; a learned projection is the same up to a low-rank factor of its ``C`` matrix).
* One ``CommStep`` module is applied P times (CommNet's module sharing across communication steps), so the
  parameter count does not depend on P and P can be changed between runs of the same architecture.
* Widths: the encoder is ``obs → hidden[:-1] → hidden[-1]`` (ReLU), the communication state has ``hidden[-1]``
  units and the head is linear. With the treadmill's ``(4096, 12)`` the P rounds run on 12 units, which keeps
  P = 5 rounds of N agents cheap; with ``(256,)`` this is exactly CommNet's encoder / comm / decoder stack.
* The mean is vectorised as ``(Σ_j m_j − m_i) / (N − 1)``; a lone agent (N = 1) hears zeros.
* ``greedy_q`` reports the *first* round's messages ``[B, N, bits]``: that is what a radio would carry before any
  agent has heard anything; later rounds depend on what was heard and are internal to the centralised pass.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.algorithm import Batch, Loss, NetworkAgent, taken, td_loss
from convoy.algos.nets import GroupLinear, GroupMLP, gumbel_bits, id_width, signalling_loss, with_agent_id
from convoy.config import IMSConfig


def mean_of_others(sent: Tensor) -> Tensor:
    """Per agent, the mean of the *other* agents' messages: ``[..., N, F]`` → ``[..., N, F]`` (zeros if N = 1)."""
    n = sent.shape[-2]
    return (sent.sum(dim=-2, keepdim=True) - sent) / max(n - 1, 1)


class CommStep(nn.Module):
    """One CommNet communication round for all agents at once; a module of its own so it can be hooked/counted."""

    def __init__(self, groups: int, width: int, bits: int, cfg: IMSConfig) -> None:
        super().__init__()
        self.bits, self.discrete, self.cfg = bits, bool(cfg.discrete), cfg
        self.speak = GroupLinear(groups, width, 2 * bits if self.discrete else bits)  # h^p → message (logits)
        self.recur = GroupLinear(groups, width, width)  # W_h
        self.listen = GroupLinear(groups, bits, width)  # W_c

    def emit(self, h: Tensor, train: bool, rand: Callable[[Tensor], Tensor] = torch.rand_like) -> Tensor:
        """Every agent's message ``[..., N, bits]`` from its hidden state."""
        out = self.speak(h)
        return gumbel_bits(out, self.bits, train, self.cfg, rand) if self.discrete else out

    def forward(
        self,
        h: Tensor,
        h0: Tensor,
        train: bool,
        received: Tensor | None = None,
        rand: Callable[[Tensor], Tensor] = torch.rand_like,
    ) -> tuple[Tensor, Tensor]:
        """Next hidden state and the messages sent this round; ``received`` replaces the averaged message."""
        sent = self.emit(h, train, rand)
        heard = mean_of_others(sent) if received is None else received
        return F.relu(self.recur(h) + self.listen(heard) + h0), sent


class IMS(NetworkAgent):
    """CommNet with P rounds of averaged messages; every round is one batched pass over all agents."""

    name = "ims"
    cfg: IMSConfig
    uses_messages = True

    def build(self) -> dict[str, nn.Module]:
        if self.cfg.message_bits is None or self.cfg.comm_iterations is None:
            raise ValueError("config: resolve env defaults first (convoy.config.resolve_algo)")
        self.bits: int = int(self.cfg.message_bits)
        self.rounds: int = int(self.cfg.comm_iterations)
        groups = 1 if self.shared else self.n_agents
        hidden = self.cfg.widths
        width = hidden[-1]
        obs_in = self.obs_dim + id_width(self.n_agents, self.shared)
        return {
            # h⁰ (ReLU applied in forward)
            "encoder": GroupMLP(groups, obs_in, hidden[:-1], width, norm=self.cfg.layer_norm),
            "comm": CommStep(groups, width, self.bits, self.cfg),
            "head": GroupLinear(groups, width, self.n_act),
        }

    def forward(
        self, nets: nn.ModuleDict, obs: Tensor, train: bool, received: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Q-values ``[..., N, A]`` and the first round's messages ``[..., N, bits]``; ``received``
        (``[..., N, bits]``) overrides the averaged message every agent hears, in every round (for channel models,
        white-noise probes and memory modules)."""
        h0 = F.relu(nets["encoder"](with_agent_id(obs, self.shared)))
        h, first = nets["comm"](h0, h0, train, received, self.rand_like)  # round 1 (P ≥ 1): the messages acting reports
        for _ in range(self.rounds - 1):  # P rounds; agents and batch stay vectorised inside each
            h, _ = nets["comm"](h, h0, train, received, self.rand_like)
        q: Tensor = nets["head"](h)  # torch leaves a module call untyped
        return q, first

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor, None]:
        q, first = self.forward(self.online, obs, train=False)
        return q, first, None

    def q_values(self, nets: nn.ModuleDict, obs: Tensor) -> Tensor:
        return self.forward(nets, obs, train=False)[0]

    def loss(self, batch: Batch) -> Loss:
        """P rounds of averaged messages → Q → double-Q target → per-agent TD losses (summed by ``update``)."""
        # the centralised pass: every round's messages stay in the graph, so each agent's loss reaches every encoder
        q = taken(self.forward(self.online, batch["obs"], train=True)[0], batch["action"])
        # double-Q target from the target copy of the whole stack
        y = self.bootstrap(self.q_values, batch)
        return Loss(td_loss(q, y, self.cfg).mean(dim=-2), *self.signalling(batch))

    def signalling(self, batch: Batch) -> tuple[Tensor | None, dict[str, float | Tensor]]:
        """The positive-signalling term (``signalling_coef``) on the first round's discrete messages."""
        if not (self.cfg.discrete and self.cfg.signalling_coef):
            return None, {}
        h0 = F.relu(self.online["encoder"](with_agent_id(batch["obs"], self.shared)))
        comm = cast(CommStep, self.online["comm"])
        return signalling_loss(comm.speak(h0), self.bits, self.cfg, self.runs)
