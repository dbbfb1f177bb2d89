"""Independent DQN with stabilised experience replay (SER), optionally with Foerster et al.'s fingerprint.

With many learners in one env, old transitions describe teammates that no longer exist (non-stationarity). The
paper's SER weighs each sampled transition's TD loss by a factor that decays linearly with the number of episodes
elapsed since it was collected: ``w = max(0, 1 − age / ser_horizon)``, so recent experience dominates the update
while the buffer keeps its size. Foerster et al. (2017) instead condition the Q-network on a *fingerprint* of the
other agents' training stage — here (ε, fraction of training done), stored with each transition and appended to
every agent's input — which the ``fingerprint`` switch adds on top.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from convoy.algos.algorithm import epsilon_at
from convoy.algos.idqn import IndependentDQN
from convoy.algos.updater import Batch, Loss
from convoy.config import SERConfig


def age_weights(episode: Tensor, episodes: int | Tensor, horizon: int) -> Tensor:
    """SER's ``max(0, 1 − age / horizon)`` per sample; age = episodes finished since its episode began."""
    age = (episodes - episode).clamp_min(0).float()
    return (1.0 - age / horizon).clamp_min(0.0)


class DQNSER(IndependentDQN):
    """Independent DQN whose sampled losses are weighted by sample age (and optionally fingerprinted)."""

    name = "dqn-ser"
    cfg: SERConfig
    FP_DIM = 2

    def input_width(self) -> int:
        return super().input_width() + (self.FP_DIM if self.cfg.fingerprint else 0)

    def fingerprint(self) -> np.ndarray:
        """(ε, training progress) as seen by the acting policy right now."""
        p = self.progress
        return np.array(
            [epsilon_at(self.cfg, p.env_steps, p.total_steps), min(1.0, p.env_steps / max(p.total_steps, 1))],
            dtype=np.float32,
        )

    def extras(self, obs: np.ndarray, state: Any = None) -> dict[str, np.ndarray]:
        if not self.cfg.fingerprint:
            return {}
        return {"fingerprint": np.broadcast_to(self.fingerprint(), (*obs.shape[:-2], self.FP_DIM)).copy()}

    def features(self, obs: Tensor, batch: Batch | None = None) -> Tensor:
        x = super().features(obs)
        if not self.cfg.fingerprint:
            return x
        if batch is not None:
            fp = batch.extras["fingerprint"]  # [M, 2]: the stage the sample was collected at
        else:
            fp = torch.as_tensor(self.fingerprint(), device=obs.device).expand(*obs.shape[:-2], self.FP_DIM)
        fp = fp.to(x.dtype).unsqueeze(-2).expand(*x.shape[:-1], self.FP_DIM)
        return torch.cat([x, fp], dim=-1)

    def loss(self, batch: Batch) -> Loss:
        """Independent DQN's TD losses, each sample weighted by its age: ``w = max(0, 1 − age / ser_horizon)``.

        Age = episodes finished since the sample's episode began: the trainer stamps every transition with
        ``episode`` = the number of episodes finished when its episode started, so ``progress.episodes − episode``
        counts the episodes collected since (in a population, each run's own episodes).
        """
        err, delta = self.td_losses(batch)
        now = torch.as_tensor(self.progress.episodes, device=self.device).reshape(-1, 1)  # [R, 1]: each run's own
        w = age_weights(batch.episode, now, self.cfg.ser_horizon)
        prioritized = "is_weight" in batch.extras  # drawn by priority: age weights times importance weights
        if prioritized:
            w = w * batch.extras["is_weight"]
        loss = (err * w.unsqueeze(-1)).sum(dim=-2) / w.sum(dim=-1, keepdim=True).clamp_min(1e-8)
        return Loss(loss, priority=delta if prioritized else None)
