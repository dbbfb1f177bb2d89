"""Independent DQN: each agent's Q-network sees only its own observation — the no-communication baseline.

The Q-network is an MLP over the flat observation, or (``encoder=entity``) the entity encoder of ``algos/entity.py``
and an MLP head.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.entity import obs_network
from convoy.algos.nets import id_width, with_agent_id
from convoy.algos.updater import Batch, Loss, bootstrap_target, taken, td_loss
from convoy.config import IDQNConfig


class IndependentDQN(NetworkAgent):
    """N independent (double) DQNs, evaluated in one batched pass; shared weights when ``share_params``."""

    name = "idqn"
    cfg: IDQNConfig

    def input_width(self) -> int:
        return self.obs_dim + id_width(self.n_agents, self.shared)

    def features(self, obs: Tensor, batch: Batch | None = None) -> Tensor:
        """Network input from observations ``[..., N, D]`` (subclasses append e.g. a fingerprint)."""
        return with_agent_id(obs, self.shared)

    def build(self) -> dict[str, nn.Module]:
        groups = 1 if self.shared else self.n_agents
        extra = self.input_width() - self.obs_dim  # agent id, fingerprint: read beside the own features
        return {"q": obs_network(self.spec, self.cfg, groups, extra, self.cfg.widths, self.n_act, q_values=True)}

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, None, None]:
        return self.online["q"](self.features(obs)), None, None

    def q_and_y(self, batch: Batch) -> tuple[Tensor, Tensor]:
        """Q_i(o_i, a_i) of the actions taken ``[M, N]`` and their double-Q targets from the target network."""
        q = taken(self.online["q"](self.features(batch.obs, batch)), batch.action)
        q_fn = lambda nets, obs: nets["q"](self.features(obs, batch))  # noqa: E731
        return q, bootstrap_target(self, q_fn, batch)

    def loss(self, batch: Batch) -> Loss:
        """Each agent's mean TD loss on its own Q-network; no agent's gradient reaches another's."""
        return Loss(td_loss(*self.q_and_y(batch), self.cfg).mean(dim=-2))
