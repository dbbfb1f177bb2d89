"""Independent DQN: each agent's Q-network sees only its own observation — the no-communication baseline."""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn

from convoy.algos.algorithm import Algorithm
from convoy.algos.nets import GroupMLP, id_width, with_agent_id
from convoy.config import IDQNConfig


class IndependentDQN(Algorithm):
    """N independent (double) DQNs, evaluated in one batched pass; shared weights when ``share_params``."""

    name = "idqn"
    config_model = IDQNConfig

    def input_width(self) -> int:
        return self.obs_dim + id_width(self.n_agents, self.shared)

    def features(self, obs: Tensor, batch: dict[str, Tensor] | None = None) -> Tensor:
        """Network input from observations ``[..., N, D]`` (subclasses append e.g. a fingerprint)."""
        return with_agent_id(obs, self.shared)

    def build(self) -> dict[str, nn.Module]:
        groups = 1 if self.shared else self.n_agents
        return {"q": GroupMLP(groups, self.input_width(), self.cfg.hidden, self.n_act)}

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, None, None]:
        return self.online["q"](self.features(obs)), None, None

    def q_and_target(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        return self.td_pair(lambda nets, obs, train: nets["q"](self.features(obs, batch)), batch)
