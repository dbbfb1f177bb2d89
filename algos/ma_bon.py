"""MA-BoN (the paper's section 4.2): one broadcast message from all agents' encodings, one pass for all Q-values.

Every agent encodes its observation, ``e_i = enc(o_i)`` (``encoding`` units). The message network f′ reads the
concatenation of *all* encodings ``[e_1 … e_N]`` and produces one broadcast message ``bm`` (``message_bits``
Gumbel-softmax bits, straight-through in training, argmax at execution). Every agent's action values then come from
``Q_i = g′(o_i, bm)``, evaluated for all N agents in one ``GroupMLP`` call over the agent axis — no P rounds as in
IMS, which is why inference grows linearly in N (section 6.2). All agents' TD losses are summed, so f′ and every
encoder receive the cumulative gradients of all agents' losses; g′_i (per-agent weights) is reached by agent i's
loss only. Targets use the target copies of every network, synced every C updates.

Choices made where the paper is silent:

* The encoder is one linear layer + ReLU per agent (shared or per-agent with ``share_params``); f′ is a single
  network (one broadcast) with the configured hidden widths, so its first layer — N·encoding inputs — is the only
  part whose size grows with N (linearly). g′ has the configured hidden widths.
* With shared weights a one-hot agent id is appended to the encoder's and g′'s inputs (``agent_id``, on by default)
  so agents with different roles can still act differently; that adds N input columns, again linear in N.
  ``agent_id=False`` is the paper's literal ``g′(z_i, bm)``, whose size is then independent of N.
* ``encoder=entity`` (``algos/entity.py``): the encoder and g′ read the observation as a set of cars, and g′ reads
  ``bm`` as one more entity; f′ still reads the N encodings in agent order.
* ``greedy_q`` reports ``bm`` repeated for every agent ``[B, N, bits]`` so that metrics and channel models see the
  same per-agent message layout as the other algorithms; all N rows of an env are identical.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.entity import obs_network
from convoy.algos.listening import HearsMessages
from convoy.algos.ma_mesn import MAMeSN
from convoy.algos.nets import GroupMLP, gumbel_bits, id_width, with_agent_id
from convoy.config import BoNConfig


class MABoN(HearsMessages, NetworkAgent):
    """Broadcast network: encoders → f′ (one message per env) → g′ for every agent in one batched call."""

    name = "ma-bon"
    cfg: BoNConfig
    uses_messages = True

    def build(self) -> dict[str, nn.Module]:
        if self.cfg.message_bits is None:
            raise ValueError("config: resolve env defaults first (convoy.config.resolve_algo)")
        self.bits: int = int(self.cfg.message_bits)
        self.senders = 1
        self.use_id: bool = self.shared and bool(self.cfg.agent_id)
        groups = 1 if self.shared else self.n_agents
        ids = id_width(self.n_agents, self.use_id)
        enc = int(self.cfg.encoding)
        return {
            "encoder": obs_network(self.spec, self.cfg, groups, ids, (), enc),  # e_i (ReLU applied in forward)
            # f′: one broadcast
            "message": GroupMLP(1, self.n_agents * enc, self.cfg.widths, 2 * self.bits, norm=self.cfg.layer_norm),
            # g′: bm one more entity with encoder=entity
            "policy": obs_network(
                self.spec, self.cfg, groups, ids, self.cfg.widths, self.n_act, 1, self.bits, q_values=True
            ),
        }

    def message_logits(self, nets: nn.ModuleDict, obs: Tensor) -> Tensor:
        """f′: the broadcast's logits ``[..., 1, 2·bits]`` of each env from all its agents' encodings."""
        e = F.relu(nets["encoder"](with_agent_id(obs, self.use_id)))  # [..., N, enc]
        joint = e.reshape(*e.shape[:-2], 1, e.shape[-2] * e.shape[-1])  # [..., 1, N·enc]
        logits: Tensor = nets["message"](joint)  # torch leaves a module call untyped
        return logits

    def speak(self, nets: nn.ModuleDict, obs: Tensor, train: bool) -> tuple[Tensor, Tensor, Tensor]:
        """(id-augmented inputs, ``bm`` per agent ``[..., N, bits]``, what each hears: the same ``bm``)."""
        x = with_agent_id(obs, self.use_id)
        bm = gumbel_bits(self.message_logits(nets, obs), self.bits, train, self.cfg, self.rand_like)
        sent = bm.expand(*x.shape[:-1], self.bits)
        return x, sent, self.control(sent)

    def listen(self, nets: nn.ModuleDict, x: Tensor, heard: Tensor) -> Tensor:
        """g′: every agent's Q-values ``[..., N, A]`` in one call."""
        q: Tensor = nets["policy"](torch.cat([x, heard], dim=-1))
        return q

    def forward(
        self, nets: nn.ModuleDict, obs: Tensor, train: bool, received: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Q-values ``[..., N, A]`` and ``bm`` per agent ``[..., N, bits]``; ``received`` (``[..., N, bits]``)
        overrides what each agent hears (for channel models, white-noise probes and memory modules)."""
        x, sent, heard = self.speak(nets, obs, train)
        return self.listen(nets, x, heard if received is None else received), sent

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor, Any]:
        x, sent, heard = self.speak(self.online, obs, False)
        return self.listen(self.online, x, self.hear(heard.contiguous())), sent.contiguous(), None

    # MA-BoN trains exactly as MA-MeSN (Algorithm 1): message → Q_i(o_i, bm) → double-Q target → per-agent TD
    # losses, summed, so every agent's loss reaches f′ and every encoder; only ``speak`` above differs.
    q_values = MAMeSN.q_values
    loss = MAMeSN.loss
    imitation_logits = MAMeSN.imitation_logits
