"""Independent DQN: each agent's Q-network sees only its own observation — the no-communication baseline.

The Q-network is an MLP over the flat observation, or (``encoder=entity``) the entity encoder of ``algos/entity.py``
and an MLP head. With ``heads`` > 1 it is Bootstrapped DQN (Osband et al. 2016, "Deep exploration via bootstrapped
DQN"): K heads on one encoder, each trained towards its own double-Q target on every sample (the heads differ by
their initial weights; no bootstrap masks, which Osband et al. found to matter little), and an exploring env drives
a whole episode on one head drawn at its start. One head is one plausible Q-function, and following it for an episode
is exploration that commits to a way of driving, where ε-greedy only dithers around the current one. An evaluation
(ε = 0) acts on the heads' mean.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.entity import obs_network
from convoy.algos.nets import id_width, with_agent_id
from convoy.algos.streams import to_integers
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
        return {"q": obs_network(self.spec, self.cfg, groups, extra, self.cfg.widths, self.n_act, q_values=True,
                                 heads=self.cfg.heads)}  # fmt: skip

    def imitation_logits(self, obs: Tensor) -> Tensor:
        """The online Q-values ``[R, b, N, A]`` as a clone's logits (``learner/imitation.py``)."""
        logits: Tensor = self.online["q"](self.features(obs))
        return logits

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, None, Tensor | None]:
        q = self.online["q"](self.features(obs))
        return (q if self.cfg.heads == 1 else self.on_heads(q, state)), None, state

    # --- Bootstrapped DQN's heads (``heads`` > 1) ----------------------------------------------------------------
    def on_heads(self, q: Tensor, head: Tensor | None) -> Tensor:
        """Q ``[R, B, N, A]`` of each env's head (``head [R, B]``), or the heads' mean where it has none (−1)."""
        mean = q.mean(dim=-2)
        if head is None:
            return mean
        index = head.clamp_min(0)[:, :, None, None, None].expand(*q.shape[:3], 1, q.shape[-1])
        return torch.where((head >= 0)[:, :, None, None], q.gather(-2, index).squeeze(-2), mean)

    def initial_state(self, num_envs: int) -> Tensor | None:
        """Each env's head ``[R, B]``, −1: none yet (one is drawn at the env's first exploring act)."""
        if self.cfg.heads == 1:
            return None
        return torch.full((self.runs, num_envs), -1, dtype=torch.long, device=self.device)

    def reset_runs(self, state: Any, done: np.ndarray) -> Any:
        """An env whose episode ended gets a new head at its next exploring act."""
        if state is None:
            return None
        return state.masked_fill(torch.as_tensor(done, device=self.device), -1)

    def act_runs(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> Any:
        """``act`` on the heads: an exploring env without a head draws one first, from its run's exploration
        stream (greedy acting draws nothing)."""
        if state is not None:
            eps = self.env_epsilon(epsilon, state.shape[1])
            need = (state < 0) & torch.as_tensor(eps > 0, device=self.device)
            drawing = need.any(dim=1)
            if bool(drawing.any()):
                advance = None if bool(drawing.all()) else drawing.long()
                drawn = to_integers(self.streams["explore"].bits(state.shape[1:], advance), self.cfg.heads)
                state = torch.where(need, drawn, state)
        return super().act_runs(obs, epsilon, state)

    # --- learning ------------------------------------------------------------------------------------------------
    def q_and_y(self, batch: Batch) -> tuple[Tensor, Tensor]:
        """Q_i(o_i, a_i) of the actions taken ``[M, N]`` and their double-Q targets from the target network; with
        heads, ``[K, M, N]``: each head's, towards its own target (the batch seen with a leading head axis)."""
        if self.cfg.heads == 1:
            q = taken(self.online["q"](self.features(batch.obs, batch)), batch.action)
            q_fn = lambda nets, obs: nets["q"](self.features(obs, batch))  # noqa: E731
            return q, bootstrap_target(self, q_fn, batch)
        k = self.cfg.heads
        per_head = batch.map(lambda v: v.expand(k, *v.shape))

        def heads_q(nets: nn.ModuleDict, obs: Tensor) -> Tensor:  # [K, M, N, A], one pass for all heads
            q: Tensor = nets["q"](self.features(obs[0], batch))
            return q.movedim(-2, 0)

        return taken(heads_q(self.online, per_head.obs), per_head.action), bootstrap_target(self, heads_q, per_head)

    def td_losses(self, batch: Batch) -> tuple[Tensor, Tensor]:
        """Each sample's TD loss per agent ``[M, N]`` and its |TD error| averaged over the agents ``[M]`` (what
        prioritized replay draws by), both the mean over the heads when there are several."""
        q, y = self.q_and_y(batch)
        err, delta = td_loss(q, y, self.cfg), (q - y).abs().mean(dim=-1)
        return (err, delta) if self.cfg.heads == 1 else (err.mean(dim=0), delta.mean(dim=0))

    def loss(self, batch: Batch) -> Loss:
        """Each agent's mean TD loss on its own Q-network; no agent's gradient reaches another's. Drawn by priority,
        each sample's loss is weighted by its importance weight (``is_weight``), and its |TD error| goes back."""
        err, delta = self.td_losses(batch)
        if "is_weight" not in batch.extras:
            return Loss(err.mean(dim=-2))
        return Loss((err * batch.extras["is_weight"].unsqueeze(-1)).mean(dim=-2), priority=delta)
