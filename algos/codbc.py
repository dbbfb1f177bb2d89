"""CoDBC (section 6.4): per-agent behaviour cloning of a trained centralised cooperative policy.

The paper's decentralised baseline: after MA-MeSN has converged, each agent learns to imitate the centralised
(expert) policy from its own observation only, so it runs without messages. It needs the expert first — which is
the point the paper makes against it (~8000 more episodes, run sequentially) and what MA-MeSN-MM avoids.

How it learns here (choices where the paper says only "imitation learning"):

* The student is one network per agent (shared with an agent id, per ``share_params``) on the agent's own
  observation; its outputs are action logits, acted on ε-greedily like every other algorithm's Q-values.
* DAgger-style data: at step 0 the teacher drives a share ``teacher_fraction`` of the envs, decaying linearly to 0
  with the ε schedule; the student drives the rest. Every visited state is labelled at update time with the
  teacher's greedy joint action (the teacher reads the *joint* observation stored in the transition and its true
  messages), so the student learns also in the states its own mistakes lead to.
* Loss: each agent's cross-entropy to the teacher's action, masked to its own action count, summed over agents.
  No target network, no bootstrapping (``gamma``, ``double_q``, ``target_update`` do not apply).
* The teacher is any trained feed-forward Convoy checkpoint of the same env shape (MA-MeSN is the paper's; MA-BoN,
  the ``-mm`` variants, IMS and the independent learners work too); DIAL (messages from t−1) and hierarchical runs
  are refused. It is loaded on first use, so evaluating a CoDBC checkpoint needs only the student.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.algorithm import NEG, ActOutput, Batch, Loss, NetworkAgent, decay_progress
from convoy.algos.nets import GroupMLP, id_width, with_agent_id
from convoy.config import CoDBCConfig
from convoy.envs.batched import EnvSpec
from convoy.validation import ConfigError

TEACHERS = ("ma-mesn", "ma-bon", "ma-mesn-mm", "ma-bon-mm", "ims", "idqn", "dqn-ser")


class CoDBC(NetworkAgent):
    """A decentralised student per agent, trained to reproduce the teacher's greedy actions."""

    name = "codbc"
    cfg: CoDBCConfig
    syncs_by_updates = False  # no bootstrapping: no target to sync

    def build(self) -> dict[str, nn.Module]:
        groups = 1 if self.shared else self.n_agents
        self._teacher: NetworkAgent | None = None
        return {
            "policy": GroupMLP(
                groups,
                self.obs_dim + id_width(self.n_agents, self.shared),
                self.cfg.widths,
                self.n_act,
                norm=self.cfg.layer_norm,
            )
        }

    @property
    def teacher(self) -> NetworkAgent:
        """The centralised policy being cloned, loaded from ``cfg.teacher`` on first use (frozen, greedy)."""
        if self._teacher is None:
            if self.cfg.teacher is None:
                raise ConfigError("teacher", "CoDBC needs a teacher checkpoint: algo_params.teacher=PATH")
            self._teacher = load_teacher(self.cfg.teacher, self.spec, str(self.device))
        return self._teacher

    def logits(self, obs: Tensor) -> Tensor:
        logits: Tensor = self.online["policy"](with_agent_id(obs, self.shared))  # torch leaves a module call untyped
        return logits.masked_fill(~self.action_mask, NEG)

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, None, None]:
        return self.logits(obs), None, None

    def teacher_actions(self, obs: Tensor) -> Tensor:
        """The teacher's greedy actions ``[..., N]`` for observations ``[..., N, D]``: one teacher (a run of one)
        for every run, its rows laid end to end."""
        q, _, _ = self.teacher.greedy_q(obs.reshape(1, -1, *obs.shape[-2:]), None)
        return q.masked_fill(~self.action_mask, NEG).argmax(dim=-1).reshape(obs.shape[:-1])

    def teacher_share(self) -> float:
        """DAgger's β: the share of envs the teacher drives — only while collecting training data."""
        p = self.progress
        if not p.training:
            return 0.0  # evaluation (and a loaded checkpoint) measures the student alone
        return self.cfg.teacher_fraction * (1.0 - decay_progress(self.cfg, p.env_steps, p.total_steps))

    @torch.no_grad()
    def act_runs(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput:
        """The student's ε-greedy actions, with the teacher driving a decaying share of the envs (DAgger's β)."""
        out = super().act_runs(obs, epsilon, state)
        beta = self.teacher_share()
        if beta > 0:  # each run draws its envs from its own exploration stream, after its exploration draw
            drive = (self.streams["explore"].uniform(obs.shape[1]) < beta).cpu().numpy()  # [R, B]
            if drive.any():
                rows = torch.as_tensor(obs[drive], dtype=torch.float32, device=self.device)
                out.actions[drive] = self.teacher_actions(rows).cpu().numpy()
        return out

    def loss(self, batch: Batch) -> Loss:
        """Each agent's cross-entropy to the teacher's greedy action in every visited state (DAgger's labels)."""
        logits = self.logits(batch["obs"])  # [R, M, N, A]
        with torch.no_grad():
            labels = self.teacher_actions(batch["obs"])  # [M, N]
            agreement = (logits.argmax(dim=-1) == labels).float().mean(dim=(-2, -1))
        ce = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), labels.flatten(), reduction="none").view_as(labels)
        return Loss(ce.mean(dim=-2), None, {"teacher_agreement": agreement})


def load_teacher(path: str, spec: EnvSpec | None, device: str = "cpu") -> NetworkAgent:
    """The frozen teacher in checkpoint ``path``, or a ConfigError naming ``teacher``: a file that is missing,
    unreadable or hostile (``read_checkpoint`` refuses it), a policy CoDBC cannot clone, or one trained on another
    env shape than ``spec`` (None: not compared)."""
    from convoy.algos.checkpoint import CheckpointError, load_checkpoint

    try:
        algo, job, _ = load_checkpoint(path, device=device)
    except CheckpointError as exc:
        raise ConfigError("teacher", str(exc)) from None
    if job.hierarchical or algo.name not in TEACHERS or not isinstance(algo, NetworkAgent):
        kind = "hierarchical " + job.algo if job.hierarchical else algo.name
        raise ConfigError(
            "teacher", f"{path} holds a {kind} policy; CoDBC clones a feed-forward one: {', '.join(TEACHERS)}"
        )
    if spec is not None and algo.spec != spec:
        raise ConfigError(
            "teacher",
            f"{path} was trained on {algo.spec}, this job's env is {spec}; train the teacher on the same env "
            "parameters",
        )
    algo.online.requires_grad_(False)
    return algo
