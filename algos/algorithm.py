"""What every algorithm shares: acting with ε-greedy over masked Q-values, replay, double-Q targets, target sync.

An algorithm object is transport-free: the in-process trainer, the tests and (later) the distributed learner all
drive it through the same four calls — ``act`` (a batch of observations → actions), ``observe`` (a chunk of joint
transitions ``[T, B, …]``), ``update`` (one gradient step when ``can_update``) and ``state_dict`` (checkpoints
and weight broadcasts). Step-based algorithms (everything but DIAL) flatten chunks into the joint replay buffer and
only implement ``q_and_target``; the per-agent TD losses are computed here so that tests can back-propagate one
agent's loss and see exactly which weights it reaches.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.nets import pick_device
from convoy.algos.replay import JointReplay
from convoy.config import AlgoConfig
from convoy.envs.batched import EnvSpec

# Updates in a row whose loss or gradient is not finite before the run fails: one is skipped (a bad batch), this
# many means the weights or the data are broken and going on would only hide it.
MAX_NONFINITE_IN_A_ROW = 100
NEG = -1e9  # Q-value given to actions an agent does not have (heterogeneous action spaces)


@dataclass
class Progress:
    """Where training stands; the trainer (or learner process) keeps it current for schedules and fingerprints."""

    env_steps: int = 0
    episodes: int = 0
    total_steps: int = 1
    training: bool = False  # set by the loops that collect training data (schedules that only apply to them)


@dataclass
class ActOutput:
    """Actions ``[B, N]`` plus what the algorithm wants stored with the transition (``extras``)."""

    actions: np.ndarray
    messages: np.ndarray | None = None  # [B, N, bits] sent this step, for metrics and the channel model
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    state: Any = None  # recurrent state to pass to the next act (DIAL's messages from t−1)


def td_target(
    reward: Tensor,
    terminated: Tensor,
    gamma: float | Tensor,
    q_next_target: Tensor,
    q_next_online: Tensor | None,
    mask: Tensor,
) -> Tensor:
    """``r + γ (1 − terminated) Q_target(s', a*)`` with ``a*`` the online argmax (double Q) or the target's.

    ``gamma`` may be one discount per sample ``[M]``: a transition that spans τ steps (an option of hierarchical
    DQN) bootstraps with γ^τ, or options that collect more steps of reward would look better for that alone.
    """
    target_q = q_next_target.masked_fill(~mask, NEG)
    if q_next_online is None:
        best = target_q.max(dim=-1).values
    else:
        a_star = q_next_online.masked_fill(~mask, NEG).argmax(dim=-1, keepdim=True)
        best = target_q.gather(-1, a_star).squeeze(-1)
    cont = (1.0 - terminated.float()).unsqueeze(-1)
    if isinstance(gamma, Tensor):
        gamma = gamma.unsqueeze(-1)
    return reward + gamma * cont * best


def decay_progress(cfg: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """How far the exploration schedule has run, 0 → 1 over min(fraction × run, max steps), then 1."""
    horizon = max(1, min(int(cfg.eps_decay_fraction * total_steps), cfg.eps_decay_max_steps))
    return min(1.0, env_steps / horizon)


def epsilon_at(cfg: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """Linear decay from ``eps_start`` to ``eps_end`` over min(fraction × run, max steps), then constant."""
    return cfg.eps_start + decay_progress(cfg, env_steps, total_steps) * (cfg.eps_end - cfg.eps_start)


class Algorithm(ABC):
    """Base class: subclasses build networks in ``build`` and define ``greedy_q`` and ``q_and_target``."""

    name: ClassVar[str]
    config_model: ClassVar[type[AlgoConfig]]
    chunk_len: int = 1  # steps per ``observe`` chunk the trainer should collect (DIAL: its unroll)
    uses_messages: ClassVar[bool] = False

    def __init__(self, spec: EnvSpec, cfg: AlgoConfig, device: str | torch.device = "auto", seed: int = 0) -> None:
        if not isinstance(cfg, self.config_model):
            raise TypeError(f"{self.name} needs a {self.config_model.__name__}, got {type(cfg).__name__}")
        if cfg.hidden is None or cfg.share_params is None:
            raise ValueError("config: resolve env defaults first (protocol.config.resolve_algo)")
        self.spec, self.cfg = spec, cfg
        self.device = pick_device(device) if isinstance(device, str) else device
        self.n_agents, self.obs_dim, self.n_act = spec.n_agents, spec.obs_dim, spec.max_actions
        self.shared: bool = bool(cfg.share_params)
        self.rng = np.random.default_rng(seed)
        self.n_actions_np = np.asarray(spec.n_actions, dtype=np.int64)
        mask = torch.arange(self.n_act)[None, :] < torch.as_tensor(spec.n_actions)[:, None]
        self.action_mask = mask.to(self.device)  # [N, A]
        self.progress = Progress()
        self.updates = 0
        self.skipped_updates = 0  # updates whose loss or gradient was not finite: no step taken
        self._nonfinite_in_a_row = 0
        self.replay = JointReplay(cfg.replay_capacity)
        # Initial weights are a function of ``seed`` alone, not of whatever the caller's global RNG holds: a run
        # built without seeding torch first (a benchmark, a notebook) repeats, and the caller's stream is untouched.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            networks = self.build()
        self.online: nn.ModuleDict = nn.ModuleDict(networks).to(self.device)
        self.target: nn.ModuleDict = copy.deepcopy(self.online)
        self.target.requires_grad_(False)
        self._optimizer: torch.optim.Optimizer | None = None

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        """Adam, made on first use: actors never update, and the first optimizer of a process costs ~2 s of imports.
        Fused: one kernel for all parameters instead of ~10 elementwise passes (2.3× faster steps on CPU)."""
        if self._optimizer is None:
            self._optimizer = torch.optim.Adam(self.online.parameters(), lr=self.cfg.lr, fused=True)
        return self._optimizer

    # --- what subclasses provide -------------------------------------------------------------------------------
    @abstractmethod
    def build(self) -> dict[str, nn.Module]:
        """The online networks by name (targets are deep copies)."""

    @abstractmethod
    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor | None, Any]:
        """Execution-mode Q-values ``[B, N, A]``, messages sent (or None) and the next recurrent state."""

    @abstractmethod
    def q_and_target(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Q of the taken actions ``[M, N]`` (with grad) and their TD targets ``[M, N]`` (no grad)."""

    # --- acting ------------------------------------------------------------------------------------------------
    def initial_state(self, num_envs: int) -> Any:
        """Recurrent state for a fresh batch of envs (None for feed-forward algorithms)."""
        return None

    def reset_state(self, state: Any, done: np.ndarray) -> Any:
        """Clear the recurrent state of envs whose episode just ended."""
        return state

    def extras(self, obs: np.ndarray, state: Any = None) -> dict[str, np.ndarray]:
        """Per-env arrays to store with each transition (a fingerprint, an observation history), given the
        observations and the recurrent state after this act; none by default."""
        return {}

    @torch.no_grad()
    def act(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput:
        """ε-greedy actions for ``obs [B, N, D]``; ε may be a scalar or one value per env (Ape-X style)."""
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        q, msgs, new_state = self.greedy_q(obs_t, state)
        actions, _, _ = self.epsilon_greedy(q, epsilon)
        return ActOutput(
            actions=actions,
            messages=None if msgs is None else msgs.cpu().numpy(),
            extras=self.extras(obs, new_state),
            state=new_state,
        )

    def epsilon_greedy(self, q: Tensor, epsilon: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(actions, greedy actions, ε per env and agent) from Q ``[B, N, A]``; random actions stay within each
        agent's own action count. At ε = 0 no random number is drawn: greedy acting (an evaluation in the middle of
        training) leaves the exploration stream, and so the training run, as it was."""
        greedy = q.masked_fill(~self.action_mask, NEG).argmax(dim=-1).cpu().numpy()
        b = q.shape[0]
        eps = np.broadcast_to(np.asarray(epsilon, dtype=np.float64).reshape(-1, 1), (b, self.n_agents))
        if not eps.any():
            return greedy, greedy, eps
        explore = self.rng.random((b, self.n_agents)) < eps
        random_a = (self.rng.random((b, self.n_agents)) * self.n_actions_np).astype(np.int64)
        return np.where(explore, random_a, greedy), greedy, eps

    # --- learning ----------------------------------------------------------------------------------------------
    def observe(self, chunk: dict[str, np.ndarray]) -> None:
        """Store a chunk of joint transitions with leading dims ``[T, B]`` (flattened into the replay)."""
        self.replay.add({k: v.reshape(-1, *v.shape[2:]) for k, v in chunk.items()})

    def can_update(self) -> bool:
        return len(self.replay) >= max(self.cfg.learning_starts, self.cfg.batch_size)

    def updates_for(self, n_transitions: int) -> float:
        """Updates owed for ``n_transitions`` newly observed joint transitions (the replay ratio)."""
        return n_transitions * self.cfg.replay_ratio / self.cfg.batch_size

    def sample(self) -> dict[str, Tensor]:
        batch = self.replay.sample(self.cfg.batch_size, self.rng)
        return {k: torch.as_tensor(v, device=self.device) for k, v in batch.items()}

    def sample_weights(self, batch: dict[str, Tensor]) -> Tensor | None:
        """Per-sample loss weights ``[M]`` (stabilised experience replay); None = uniform."""
        return None

    def agent_losses(self, batch: dict[str, Tensor]) -> Tensor:
        """Each agent's mean TD loss ``[N]``; their sum is what ``update`` minimises."""
        q, y = self.q_and_target(batch)
        err = self.td_error(q, y)
        w = self.sample_weights(batch)
        if w is None:
            return err.mean(dim=0)
        return (err * w.unsqueeze(-1)).sum(dim=0) / w.sum().clamp_min(1e-8)

    def td_error(self, q: Tensor, y: Tensor) -> Tensor:
        """Elementwise TD loss: Huber (clipped error) or the paper's squared error, per the ``huber`` switch."""
        return F.smooth_l1_loss(q, y, reduction="none") if self.cfg.huber else 0.5 * (q - y) ** 2

    def update(self) -> dict[str, float]:
        """One gradient step on a sampled batch; syncs the targets every ``target_update`` updates."""
        batch = self.sample()
        losses = self.agent_losses(batch)
        loss = losses.sum()
        aux, stats = self.aux_loss(batch)
        total = loss if aux is None else loss + aux
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.online.parameters(), self.cfg.grad_clip)
        loss_value, norm = float(loss.detach()), float(grad_norm)
        if not (np.isfinite(loss_value) and np.isfinite(norm)):
            return self._skip_update(loss_value, norm)
        self._nonfinite_in_a_row = 0
        self.optimizer.step()
        self.updates += 1
        self.after_update()
        return {"loss": loss_value, "grad_norm": norm, **stats}

    def _skip_update(self, loss_value: float, norm: float) -> dict[str, float]:
        """A non-finite loss or gradient never reaches the weights; many in a row end the run with the cause."""
        self.optimizer.zero_grad(set_to_none=True)
        self.skipped_updates += 1
        self._nonfinite_in_a_row += 1
        if self._nonfinite_in_a_row >= MAX_NONFINITE_IN_A_ROW:
            raise FloatingPointError(
                f"{self.name}: {self._nonfinite_in_a_row} updates in a row had a non-finite loss ({loss_value}) or "
                f"gradient norm ({norm}); the weights were kept as they were. Check the env's rewards and "
                "observations for NaN/inf, or lower lr"
            )
        return {"loss": float("nan"), "grad_norm": float("nan")}

    def aux_loss(self, batch: dict[str, Tensor]) -> tuple[Tensor | None, dict[str, float]]:
        """A loss trained alongside the TD losses on the same batch (the memory modules' supervised message
        prediction) and figures to report with it; none by default."""
        return None, {}

    def after_update(self) -> None:
        """Sync the targets every ``target_update`` updates, or move them a step ``target_tau`` towards the online
        weights after every update (DIAL syncs by episodes instead)."""
        if self.cfg.target_tau < 1.0:
            target, online = list(self.target.parameters()), list(self.online.parameters())
            with torch.no_grad():
                torch._foreach_lerp_(target, online, self.cfg.target_tau)
        elif self.updates % self.cfg.target_update == 0:
            self.sync_target()

    def sync_target(self) -> None:
        self.target.load_state_dict(self.online.state_dict())

    # --- persistence -------------------------------------------------------------------------------------------
    def policy_state(self) -> dict[str, Tensor]:
        """What an actor needs to act: the online weights (on CPU, for the wire or a file)."""
        return {k: v.detach().cpu() for k, v in self.online.state_dict().items()}

    def load_policy_state(self, state: dict[str, Tensor]) -> None:
        self.online.load_state_dict(state)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume learning exactly: networks, targets, optimizer, counters, RNG."""
        return {
            "online": self.online.state_dict(),
            "target": self.target.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.online.load_state_dict(state["online"])
        self.target.load_state_dict(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])
        self.rng.bit_generator.state = state["rng"]

    # --- helpers for subclasses --------------------------------------------------------------------------------
    def td_pair(
        self, q_fn: Callable[[nn.ModuleDict, Tensor, bool], Tensor], batch: dict[str, Tensor]
    ) -> tuple[Tensor, Tensor]:
        """Q of the taken actions (online, training mode) and their double-Q targets, for any
        ``q_fn(nets, obs, train) → Q [..., N, A]``: what ``q_and_target`` is for every feed-forward algorithm."""
        q = q_fn(self.online, batch["obs"], True).gather(-1, batch["action"].unsqueeze(-1)).squeeze(-1)
        with torch.no_grad():
            q_next_t = q_fn(self.target, batch["next_obs"], False)
            q_next_o = q_fn(self.online, batch["next_obs"], False) if self.cfg.double_q else None
            y = self.target_for(q_next_t, q_next_o, batch)
            if self.cfg.advantage_learning:
                y = y - self.cfg.advantage_learning * self.action_gap(q_fn(self.target, batch["obs"], False), batch)
        return q, y

    def action_gap(self, q_target: Tensor, batch: dict[str, Tensor]) -> Tensor:
        """``max_b Q̄(s, b) − Q̄(s, a)`` of the taken actions ``[M, N]``: what advantage learning subtracts."""
        best = q_target.masked_fill(~self.action_mask, NEG).max(dim=-1).values
        return best - q_target.gather(-1, batch["action"].unsqueeze(-1)).squeeze(-1)

    def target_for(self, q_next_target: Tensor, q_next_online: Tensor | None, batch: dict[str, Tensor]) -> Tensor:
        """TD target for this batch, honouring the ``double_q`` switch and a per-sample ``discount`` if stored."""
        return td_target(
            batch["reward"],
            batch["terminated"],
            batch.get("discount", self.cfg.gamma),
            q_next_target,
            q_next_online if self.cfg.double_q else None,
            self.action_mask,
        )

    def n_parameters(self) -> int:
        return sum(p.numel() for p in self.online.parameters())
