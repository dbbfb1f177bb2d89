"""DIAL (Foerster et al. 2016): one C-Net per agent gives Q-values *and* a message, learned end to end.

Agent i's C-Net sees its own observation and the messages the other agents sent at t−1 (the paper's point against
DIAL: messages describe the past, ``m_{−i}^t(z_{−i}^{t−1})``) and outputs Q-values for its actions plus one logit
per message bit. The logits pass through the discretise/regularise unit (``dru``): in centralised training it is
``sigmoid(logit + N(0, σ²))``, a continuous, differentiable channel that the noise pushes towards saturation; at
execution it is the hard threshold ``logit > 0``, so exactly ``bits`` bits travel. Because training messages are
differentiable, agent j's TD error reaches agent i's C-Net through the message i sent one step earlier, across agents
and time, by back-propagation through an unrolled sequence.

Learning is on-policy by default: each observed chunk ``[T, B]`` (``chunk_len = unroll``) is one sequence batch that
gets exactly one update and is then dropped. The unroll restarts from the stored (detached) received messages
``msg_in`` at the chunk's first step — truncated BPTT — and from zeros after every finished episode. Targets are
double-Q values of a target-network unroll, synced every ``target_update_episodes`` finished episodes (not every C
updates). ``replay=True`` is the variant the paper used on the particle envs: chunks go to a bounded ring of
fixed-length sequences and every step's TD loss is weighted by a clipped importance ratio (see ``DIAL.is_weights``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from convoy.algos.algorithm import (
    NEG,
    ActOutput,
    Batch,
    Loss,
    NetworkAgent,
    epsilon_at,
    td_loss,
    td_target,
    with_run_axis,
)
from convoy.algos.nets import GroupMLP, gather_others, id_width, others_index, with_agent_id
from convoy.algos.replay import JointReplay
from convoy.config import DIALConfig, resolved
from convoy.envs.batched import EnvSpec

# Fields of an observed chunk that learning needs (anything else the trainer adds is not kept).
SEQ_KEYS: tuple[str, ...] = ("obs", "action", "reward", "next_obs", "terminated", "truncated", "msg_in")
MAX_PENDING = 8  # on-policy chunks waiting for their update; older ones are stale and dropped


def dru(logits: Tensor, sigma: float, train: bool, randn: Callable[[Tensor], Tensor] = torch.randn_like) -> Tensor:
    """DIAL's discretise/regularise unit: noisy sigmoid in training (differentiable), hard 0/1 at execution.

    The noise makes only saturated logits carry information reliably, so the learned code survives the switch to
    the hard threshold. ``randn`` draws it (the agent's own generators).
    """
    if not train:
        return (logits > 0).to(logits.dtype)
    if sigma > 0:
        logits = logits + sigma * randn(logits)
    return torch.sigmoid(logits)


class DIAL(NetworkAgent):
    """Differentiable inter-agent learning; all agents' C-Nets evaluated in one batched pass per time step."""

    name = "dial"
    cfg: DIALConfig
    uses_messages = True
    syncs_by_updates = False  # targets follow finished episodes (``observe``), each run's own in a population

    def __init__(
        self, spec: EnvSpec, cfg: DIALConfig, device: str | torch.device = "auto", seed: int | Sequence[int] = 0
    ) -> None:
        super().__init__(spec, cfg, device=device, seed=seed)
        self.chunk_len = int(cfg.unroll)
        self.seq_len = int(cfg.unroll)
        self.n_actions_t = torch.as_tensor(spec.n_actions, dtype=torch.float32, device=self.device)  # [N]
        # Replay (when on) holds whole sequences: one row = ``unroll`` steps of one env.
        self.replay = JointReplay(max(1, cfg.replay_capacity // self.seq_len), runs=self.runs, device=self.device)
        self.pending: deque[dict[str, np.ndarray]] = deque(maxlen=MAX_PENDING)
        self.last_chunk_rows = 0
        self.t_dim = 1  # batches are per run, time-major: [R, T, B, …]
        # finished episodes seen in observed chunks (drives target syncs) and their count at the last sync, per run
        self.episodes_done = np.zeros(self.runs, dtype=np.int64)
        self.synced_at = np.zeros(self.runs, dtype=np.int64)

    def randn(self, x: Tensor) -> Tensor:
        """The DRU's noise: normals from each run's own noise stream."""
        return self.rand_like(x, normal=True)

    # --- networks ----------------------------------------------------------------------------------------------
    def build(self) -> dict[str, nn.Module]:
        self.bits = resolved(self.cfg.message_bits, "message_bits")
        self.peers = others_index(self.n_agents).to(self.device)
        groups = 1 if self.shared else self.n_agents
        width = self.obs_dim + id_width(self.n_agents, self.shared) + (self.n_agents - 1) * self.bits
        return {"cnet": GroupMLP(groups, width, self.cfg.widths, self.n_act + self.bits, norm=self.cfg.layer_norm)}

    def cnet(self, nets: nn.ModuleDict, obs: Tensor, heard: Tensor) -> tuple[Tensor, Tensor]:
        """Q-values ``[..., N, A]`` and message logits ``[..., N, bits]`` from obs and received messages."""
        out = nets["cnet"](torch.cat([with_agent_id(obs, self.shared), heard], dim=-1))
        return out[..., : self.n_act], out[..., self.n_act :]

    def hear(self, sent: Tensor) -> Tensor:
        """What each agent receives from the others: ``[..., N, bits]`` → ``[..., N, (N−1)·bits]``."""
        return gather_others(sent, self.peers)

    def unroll(
        self, nets: nn.ModuleDict, obs: Tensor, heard0: Tensor, done: Tensor, train: bool = True
    ) -> tuple[Tensor, Tensor]:
        """Run a sequence ``obs [T, B, N, D]`` through time: Q ``[T, B, N, A]`` and messages sent ``[T, B, N, bits]``.

        Step t hears what the others sent at t−1 (``heard0`` at t = 0, zeros after a ``done`` step), and with
        ``train`` those messages stay in the graph, so a loss at t reaches every sender's C-Net at t−1, t−2, ….
        """
        keep = (~done).to(obs.dtype)[..., None, None]  # [T, B, 1, 1]
        heard, qs, sent_all = heard0, [], []
        for t in range(obs.shape[self.t_dim]):
            q, logits = self.cnet(nets, obs.select(self.t_dim, t), heard)
            sent = dru(logits, self.cfg.dru_sigma, train, self.randn)
            qs.append(q)
            sent_all.append(sent)
            heard = self.hear(sent) * keep.select(self.t_dim, t)
        return torch.stack(qs, dim=self.t_dim), torch.stack(sent_all, dim=self.t_dim)

    # --- acting ------------------------------------------------------------------------------------------------
    def initial_state(self, num_envs: int) -> Tensor:
        """No message has been sent before an episode's first step."""
        return torch.zeros(self.runs, num_envs, self.n_agents, self.bits, device=self.device)

    def reset_runs(self, state: Any, done: np.ndarray) -> Any:
        if state is None:
            return None
        keep = torch.as_tensor(~done, device=self.device).to(state.dtype)
        return state * keep[..., None, None]

    def execute(self, obs: Tensor, state: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """Execution-mode step: Q-values, hard messages sent now and the messages heard (from ``state``)."""
        if state is None:
            state = self.initial_state(obs.shape[-3])
        heard = self.hear(state)
        q, logits = self.cnet(self.online, obs, heard)
        return q, dru(logits, self.cfg.dru_sigma, train=False), heard

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor, Tensor]:
        q, sent, _ = self.execute(obs, state)
        return q, sent, sent

    @torch.no_grad()
    def act_runs(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput:
        """ε-greedy actions, plus the extras a sequence needs to restart mid-episode: ``msg_in`` (messages heard,
        ``[R, B, N, (N−1)·bits]``) and ``mu`` (behaviour probability of each taken action, ``[R, B, N]``, for
        replay)."""
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        q, sent, heard = self.execute(obs_t, state)
        actions, greedy, eps = self.explore(q, epsilon)
        mu = (1.0 - eps) * (actions == greedy) + eps / self.n_actions_np
        extras = {**self.extras(obs), "msg_in": heard.cpu().numpy(), "mu": mu.astype(np.float32)}
        return ActOutput(actions=actions, messages=sent.cpu().numpy(), extras=extras, state=sent)

    # --- data --------------------------------------------------------------------------------------------------
    def observe(self, chunk: dict[str, np.ndarray], valid: np.ndarray | None = None) -> None:
        """Count finished episodes (target sync), then queue the chunk (on-policy) or store its sequences."""
        if valid is not None:
            raise ValueError("valid: DIAL takes whole chunks (hierarchical DIAL trains one seed per process)")
        keys = (*SEQ_KEYS, "mu") if self.cfg.replay else SEQ_KEYS
        missing = [k for k in keys if k not in chunk]
        if missing:
            raise KeyError(f"DIAL chunk lacks {missing}: collect it with DIAL.act and stack out.extras into it")
        data = with_run_axis({k: chunk[k] for k in keys}, self.runs)  # [T, R, B, …]
        ended = data["terminated"] | data["truncated"]
        self.episodes_done += ended.sum(axis=(0, -1))
        due = self.episodes_done - self.synced_at >= self.cfg.target_update_episodes  # per run [R]
        if due.any():
            self.sync_runs(due)
            self.synced_at = np.where(due, self.episodes_done, self.synced_at)
        self.last_chunk_rows = ended.shape[0] * ended.shape[-1]
        if self.cfg.replay:
            self.replay.add(self.run_sequences(data))
        else:
            self.pending.append(data)

    def to_sequences(self, data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``[T, B, …]`` → rows ``[S, L, …]`` of length L = ``unroll`` (split, zero-padded; ``valid`` marks real
        steps), so chunks of any length fit one fixed-shape ring."""
        t, b = data["terminated"].shape
        length = self.seq_len
        pieces = -(-t // length)
        pad = pieces * length - t

        def cut(v: np.ndarray) -> np.ndarray:
            v = np.concatenate([v, np.zeros((pad, *v.shape[1:]), v.dtype)]) if pad else v
            v = v.reshape(pieces, length, *v.shape[1:]).swapaxes(1, 2)  # [P, B, L, ...]
            return v.reshape(pieces * b, length, *v.shape[3:])

        rows = {k: cut(v) for k, v in data.items()}
        valid = np.arange(pieces * length).reshape(pieces, 1, length) < t
        rows["valid"] = np.broadcast_to(valid, (pieces, b, length)).reshape(pieces * b, length)
        return rows

    def run_sequences(self, data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """A chunk ``[T, R, B, …]`` → each run's sequences ``[R, S, L, …]``, in a single run's order."""
        t, r, b = data["terminated"].shape
        rows = self.to_sequences({k: v.reshape(t, r * b, *v.shape[3:]) for k, v in data.items()})
        return {
            k: v.reshape(-1, r, b, *v.shape[1:]).swapaxes(0, 1).reshape(r, -1, *v.shape[1:]) for k, v in rows.items()
        }

    def reserve_replay(self, env_steps: int) -> None:
        """One row per ``unroll`` steps of one env (a chunk of T = unroll steps of B envs is B rows)."""
        self.replay.reserve(max(1, -(-env_steps // self.seq_len)))

    def can_update(self) -> bool:
        if not self.cfg.replay:
            return bool(self.pending)
        return len(self.replay) > 0 and len(self.replay) * self.seq_len >= self.cfg.learning_starts

    def updates_for(self, n_transitions: int) -> float:
        """On-policy: one update per observed chunk. Replay: ``replay_ratio`` sampled steps per inserted step,
        with ``batch_size`` sequences of ``unroll`` steps per update."""
        if not self.cfg.replay:
            return n_transitions / self.last_chunk_rows if self.last_chunk_rows else 0.0
        return n_transitions * self.cfg.replay_ratio / (self.cfg.batch_size * self.seq_len)

    def sample(self) -> Batch:
        """The next sequence batch ``[T, B, …]``: the oldest queued chunk (on-policy) or ``batch_size`` sequences
        drawn uniformly from the ring."""
        if self.cfg.replay:  # drawn and gathered on the device
            rows = self.replay.sample(self.cfg.batch_size, self.streams["replay"])
            return {k: v.transpose(self.t_dim, self.t_dim + 1).contiguous() for k, v in rows.items()}  # [(R,) L, n, …]
        data = {k: v.swapaxes(0, 1) for k, v in self.pending.popleft().items()}  # [T, R, B, …] → [R, T, B, …]
        return {k: torch.as_tensor(np.ascontiguousarray(v), device=self.device) for k, v in data.items()}

    # --- learning ----------------------------------------------------------------------------------------------
    def sequence_q(self, batch: Batch) -> tuple[Tensor, Tensor, Tensor]:
        """All Q-values ``[T, B, N, A]`` (training unroll, with grad), Q of the taken actions and their double-Q
        TD targets ``[T, B, N]``.

        The targets need Q at ``next_obs[t]`` with the messages sent at t; evaluating every next_obs in one batched
        pass (rather than reusing step t+1) also covers truncated steps (bootstrap from the final obs) and the
        chunk's last step. Target messages come from the target network's own unroll; both use the training DRU,
        as in Foerster et al.'s implementation, so the target sees the inputs the online net is trained on.
        """
        obs, done = batch["obs"], batch["terminated"] | batch["truncated"]
        heard0 = batch["msg_in"].select(self.t_dim, 0).float()  # what was heard at the first step; detached data
        q_all, sent = self.unroll(self.online, obs, heard0, done, train=True)
        q = q_all.gather(-1, batch["action"].unsqueeze(-1)).squeeze(-1)
        with torch.no_grad():
            _, sent_target = self.unroll(self.target, obs, heard0, done, train=True)
            q_next_t, _ = self.cnet(self.target, batch["next_obs"], self.hear(sent_target))
            q_next_o = (
                self.cnet(self.online, batch["next_obs"], self.hear(sent.detach()))[0] if self.cfg.double_q else None
            )
            gamma = self.gamma if isinstance(self.gamma, float) else self.gamma.reshape(-1, 1, 1)  # [R, T, B]
            y = td_target(batch["reward"], batch["terminated"], gamma, q_next_t, q_next_o, self.action_mask)
        return q_all, q, y

    def is_weights(self, q_all: Tensor, batch: Batch) -> Tensor:
        """Per-step importance weights ``[T, B]`` for replayed sequences: ``min(1, Π_i π_i(a_i) / μ_i(a_i))``.

        π is the current ε-greedy policy (greedy w.r.t. the training unroll's Q, ε from the schedule at the current
        progress), μ the behaviour probability stored at acting time. The product over agents is the joint
        policy's ratio — the TD error of every agent depends on all agents' actions. Ratios are per step rather
        than products over time (which vanish within a few steps) and clipped to ≤ 1 as in truncated importance
        sampling (Retrace, ACER), so stale, off-policy steps are down-weighted but no step is ever amplified.
        """
        eps = epsilon_at(self.cfg, self.progress.env_steps, self.progress.total_steps)
        greedy = q_all.detach().masked_fill(~self.action_mask, NEG).argmax(dim=-1)
        pi = (1.0 - eps) * (batch["action"] == greedy).float() + eps / self.n_actions_t
        return (pi / batch["mu"].clamp_min(1e-8)).prod(dim=-1).clamp(max=1.0)

    def loss(self, batch: Batch) -> Loss:
        """One sequence batch: the unroll (messages through time) → Q → double-Q targets → each agent's TD loss
        ``[N]``, a mean over steps and envs (importance-weighted under replay)."""
        q_all, q, y = self.sequence_q(batch)
        err = td_loss(q, y, self.cfg)
        valid = batch["valid"].float() if "valid" in batch else torch.ones_like(err[..., 0])
        w = valid * self.is_weights(q_all, batch) if self.cfg.replay else valid
        steps = valid.sum(dim=(-2, -1)).clamp_min(1.0).unsqueeze(-1)  # per run
        return Loss((err * w.unsqueeze(-1)).sum(dim=(-3, -2)) / steps)

    # --- persistence -------------------------------------------------------------------------------------------
    def member_state(self, k: int) -> dict[str, Any]:
        return {"episodes_done": int(self.episodes_done[k]), "synced_at": int(self.synced_at[k])}  # noise: a stream

    def load_member_extra(self, k: int, state: dict[str, Any]) -> None:
        self.episodes_done[k] = int(state["episodes_done"])
        self.synced_at[k] = int(state["synced_at"])
