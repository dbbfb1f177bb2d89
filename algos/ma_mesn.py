"""MA-MeSN (the paper's Algorithm 1): separate message networks f′ and policy networks f″.

Every agent j turns its *current* observation into a discrete message ``m_j = f′_j(o_j)`` (Gumbel-softmax bits,
straight-through in training, argmax at execution). Agent i's policy network sees its own observation and the
messages of the *others*: ``Q_i = f″_i(o_i, m_{−i})``. The loss is the sum of all agents' TD losses, so each
message network f′_j receives the summed gradients of every other agent's TD loss (Algorithm 1's "collect
gradients from all policy networks"), while f″_i is reached by agent i's loss only. Targets use the target copies
of both networks, synced every C updates.

With ``encoder=entity`` (``algos/entity.py``) f′ and f″ read the observation as a set of cars and f″ reads each
heard message m_j as one more entity; the messages still reach f″ straight-through, so the gradients are Algorithm 1's.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.entity import obs_network
from convoy.algos.listening import HearsMessages
from convoy.algos.nets import (
    gather_others,
    gumbel_bits,
    id_width,
    others_index,
    signalling_loss,
    with_agent_id,
)
from convoy.algos.updater import Batch, Loss, bootstrap_target, taken, td_loss
from convoy.config import MeSNConfig, resolved


class MAMeSN(HearsMessages, NetworkAgent):
    """Message-sharing network; all agents' messages and Q-values come from one batched pass each."""

    name = "ma-mesn"
    cfg: MeSNConfig
    uses_messages = True

    def build(self) -> dict[str, nn.Module]:
        self.bits = resolved(self.cfg.message_bits, "message_bits")
        self.peers = others_index(self.n_agents).to(self.device)
        self.senders = self.n_agents - 1
        groups = 1 if self.shared else self.n_agents
        ids, widths = id_width(self.n_agents, self.shared), self.cfg.widths
        return {  # MLPs over [o_i, id] and [o_i, id, m_−i], or entity encoders reading each m_j as one more entity
            "message": obs_network(self.spec, self.cfg, groups, ids, widths, 2 * self.bits),  # f′
            "policy": obs_network(  # f″
                self.spec, self.cfg, groups, ids, widths, self.n_act, self.senders, self.bits, q_values=True
            ),
        }

    def message_logits(self, nets: nn.ModuleDict, obs: Tensor) -> Tensor:
        """f′: every agent's message logits ``[..., N, 2·bits]`` from its own observation."""
        logits: Tensor = nets["message"](with_agent_id(obs, self.shared))  # torch leaves a module call untyped
        return logits

    def speak(self, nets: nn.ModuleDict, obs: Tensor, train: bool) -> tuple[Tensor, Tensor, Tensor]:
        """(id-augmented inputs, every agent's message ``[..., N, bits]``, what each hears ``[..., N, (N−1)·bits]``)."""
        sent = gumbel_bits(self.message_logits(nets, obs), self.bits, train, self.cfg, self.rand_like)
        return with_agent_id(obs, self.shared), sent, self.control(gather_others(sent, self.peers))

    def listen(self, nets: nn.ModuleDict, x: Tensor, heard: Tensor) -> Tensor:
        """f″: Q-values ``[..., N, A]`` from each agent's own input and the messages it heard."""
        q: Tensor = nets["policy"](torch.cat([x, heard], dim=-1))
        return q

    def forward(
        self, nets: nn.ModuleDict, obs: Tensor, train: bool, received: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Q-values ``[..., N, A]`` and the messages sent; ``received`` overrides what each agent hears
        (``[..., N, (N−1)·bits]``: for channel models, white-noise probes and memory modules)."""
        x, sent, heard = self.speak(nets, obs, train)
        return self.listen(nets, x, heard if received is None else received), sent

    def imitation_logits(self, obs: Tensor) -> Tensor:
        """Q-values ``[R, b, N, A]`` as a clone's logits, through the channel as in training (straight-through
        bits): imitating a teacher that knows what teammates see teaches the speakers to say it."""
        return self.forward(self.online, obs, train=True)[0]

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor, Any]:
        x, sent, heard = self.speak(self.online, obs, False)
        return self.listen(self.online, x, self.hear(heard)), sent, None

    def q_values(self, nets: nn.ModuleDict, obs: Tensor) -> Tensor:
        """Execution-mode Q-values of any copy of the networks (targets, double-Q's online pick)."""
        return self.forward(nets, obs, train=False)[0]

    def loss(self, batch: Batch) -> Loss:
        """Algorithm 1 on one batch: messages → Q → double-Q target → per-agent TD losses (summed by ``update``)."""
        # every agent's message m_j = f′_j(o_j) (Gumbel bits, straight-through) and what agent i hears: m_−i
        x, _, heard = self.speak(self.online, batch.obs, train=True)
        if not self.cfg.speakers_learn:  # the listeners learn; the speakers keep what they say (a DAgger protocol)
            heard = heard.detach()
        # Q_i = f″_i(o_i, m_−i) of the actions taken
        q = taken(self.listen(self.online, x, heard), batch.action)
        # double-Q target: the target copies of f′ and f″ at o′, the action picked by the online pair
        y = bootstrap_target(self, self.q_values, batch)
        # per-agent TD losses: their sum sends every other agent's gradient into each f′_j ("collect gradients")
        td = td_loss(q, y, self.cfg).mean(dim=-2)
        if not self.cfg.signalling_coef:
            return Loss(td)
        # positive signalling (off on the treadmill): −coef·I(o; m) over the batch, from f′'s logits
        return Loss(td, *signalling_loss(self.message_logits(self.online, batch.obs), self.bits, self.cfg, self.runs))
