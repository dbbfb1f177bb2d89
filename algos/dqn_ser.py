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

from convoy.algos.idqn import IndependentDQN
from convoy.config import SERConfig


class DQNSER(IndependentDQN):
    """Independent DQN whose sampled losses are weighted by sample age (and optionally fingerprinted)."""

    name = "dqn-ser"
    config_model = SERConfig
    FP_DIM = 2

    def input_width(self) -> int:
        return super().input_width() + (self.FP_DIM if self.cfg.fingerprint else 0)

    def fingerprint(self) -> np.ndarray:
        """(ε, training progress) as seen by the acting policy right now."""
        from convoy.algos.algorithm import epsilon_at

        p = self.progress
        return np.array(
            [epsilon_at(self.cfg, p.env_steps, p.total_steps), min(1.0, p.env_steps / max(p.total_steps, 1))],
            dtype=np.float32,
        )

    def extras(self, obs: np.ndarray, state: Any = None) -> dict[str, np.ndarray]:
        if not self.cfg.fingerprint:
            return {}
        return {"fingerprint": np.broadcast_to(self.fingerprint(), (obs.shape[0], self.FP_DIM)).copy()}

    def features(self, obs: Tensor, batch: dict[str, Tensor] | None = None) -> Tensor:
        x = super().features(obs)
        if not self.cfg.fingerprint:
            return x
        if batch is not None:
            fp = batch["fingerprint"]  # [M, 2]: the stage the sample was collected at
        else:
            fp = torch.as_tensor(self.fingerprint(), device=obs.device).expand(obs.shape[0], self.FP_DIM)
        fp = fp.to(x.dtype).unsqueeze(-2).expand(*x.shape[:-1], self.FP_DIM)
        return torch.cat([x, fp], dim=-1)

    def sample_weights(self, batch: dict[str, Tensor]) -> Tensor:
        """``1 − age/horizon`` clipped at 0; age = episodes finished since the sample's episode began.

        The trainer stamps every transition with ``episode`` = the number of episodes finished when its episode
        started, so ``progress.episodes − episode`` counts the episodes collected since.
        """
        age = (self.progress.episodes - batch["episode"]).clamp_min(0).float()
        return (1.0 - age / self.cfg.ser_horizon).clamp_min(0.0)
