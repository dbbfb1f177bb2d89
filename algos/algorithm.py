"""What the algorithms share: the agent protocol trainers and actors drive, and the small pieces every value
learner is made of (ε-greedy acting, the double-Q TD target, the TD loss, target sync, a guarded gradient step).

Each algorithm file reads top to bottom beside its paper: its networks (``build``), how it acts (``greedy_q``)
and its ``loss(batch)`` written out in Algorithm 1's order. One base holds the plumbing so that no file repeats
it: :class:`NetworkAgent` (online and target networks, Adam, ε-greedy ``act``, the joint replay every step-based
learner samples from, one guarded ``update`` of ``loss``, checkpoints). DIAL learns from sequences and overrides
the data path; hierarchical DQN wraps two agents; both fit :class:`Agent`.
"""

from __future__ import annotations

import copy
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple, Protocol, overload

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.nets import pick_device, run_state, stack_runs
from convoy.algos.replay import JointReplay
from convoy.algos.streams import STREAMS, RunStreams, legacy_counter, to_integers, to_uniform
from convoy.config import ALGORITHMS, AlgoConfig
from convoy.envs.batched import EnvSpec
from convoy.transition import schema

# Updates in a row whose loss or gradient is not finite before the run fails: one is skipped (a bad batch), this
# many means the weights or the data are broken and going on would only hide it. Checked when the figures are read
# (``Figures``), not in the update: the trainer reads them every ``READ_EVERY`` updates (learner/core.py).
MAX_NONFINITE_IN_A_ROW = 100
NEG = -1e9  # Q-value given to actions an agent does not have (heterogeneous action spaces)

Batch = dict[str, Tensor]
QFn = Callable[[nn.ModuleDict, Tensor], Tensor]  # (networks, observations [M, N, D]) → Q [M, N, A]


@dataclass
class Progress:
    """Where training stands; the trainer (or learner process) keeps it current for schedules and fingerprints."""

    env_steps: int = 0
    episodes: int | np.ndarray = 0  # one count for every run, or one per run [R]
    total_steps: int = 1
    training: bool = False  # set by the loops that collect training data (schedules that only apply to them)


@dataclass
class ActOutput:
    """Actions ``[R, B, N]`` plus what the algorithm wants stored with the transition (``extras``)."""

    actions: np.ndarray
    messages: np.ndarray | None = None  # [R, B, N, bits] sent this step, for metrics and the channel model
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    state: Any = None  # recurrent state to pass to the next act (DIAL's messages from t−1), with the run axis

    def shaped(self, lead: tuple[int, ...]) -> ActOutput:
        """This output ``[R, B, …]`` with the caller's leading dims ``lead`` (a single run's ``(B,)`` leaves the
        run axis out); the recurrent state keeps the run axis, as ``act`` and ``reset_state`` take it back."""

        def like(v: np.ndarray) -> np.ndarray:
            return v.reshape(*lead, *v.shape[2:])

        messages = None if self.messages is None else like(self.messages)
        return ActOutput(like(self.actions), messages, {k: like(v) for k, v in self.extras.items()}, self.state)


def with_run_axis(chunk: dict[str, np.ndarray], runs: int) -> dict[str, np.ndarray]:
    """A chunk ``[T, R, B, …]`` as it is, or a single run's ``[T, B, …]`` with its run axis put in (the leading
    dims read from ``terminated``, ``[T, B]`` or ``[T, R, B]``)."""
    lead = np.ndim(chunk["terminated"]) if "terminated" in chunk else 3
    return {k: np.reshape(v, (np.shape(v)[0], runs, -1, *np.shape(v)[lead:])) for k, v in chunk.items()}


def cuda_graph_options() -> dict[str, Any]:
    """Inductor's options for the step on CUDA: replayed as a CUDA graph (what ``mode="reduce-overhead"`` sets),
    loop reordering after fusion off — torch 2.11's inductor asserts on the per-run Adam's foreach kernels there
    (seen on an H200; 2.13 does not), and it only tunes memory order inside fused kernels."""
    from torch._inductor import config  # imported when a step is compiled, not with the package

    return {"triton.cudagraphs": True, **{k: False for k in ("loop_ordering_after_fusion",) if hasattr(config, k)}}


class Loss(NamedTuple):
    """What one batch costs: each agent's loss ``[N]`` (their sum is minimised), an auxiliary term trained on the
    same batch (positive signalling, a memory module's message prediction) and figures to report."""

    agents: Tensor  # [R, N]
    extra: Tensor | None = None  # [R]
    stats: dict[str, float | Tensor] = {}  # noqa: RUF012  (a NamedTuple default, never mutated)

    def plus(self, extra: Tensor | None, stats: Mapping[str, float | Tensor]) -> Loss:
        """This loss with one more auxiliary term and its figures."""
        total = self.extra if extra is None else extra if self.extra is None else self.extra + extra
        return Loss(self.agents, total, {**self.stats, **stats})


class Figures(ABC):
    """One update's figures (loss, gradient norm, the algorithm's own), left on the device where they were
    computed: reading them is a host sync, so an update never reads them and the trainer reads many updates' at
    once (:func:`read_figures`). Reading is also where a run that had ``MAX_NONFINITE_IN_A_ROW`` non-finite updates
    in a row fails, with a ``FloatingPointError``."""

    @abstractmethod
    def tensors(self) -> list[Tensor]:
        """The device tensors reading copies to the host."""

    @abstractmethod
    def rows(self, host: list[np.ndarray]) -> list[dict[str, float]]:
        """One dict of figures per run (a single run's: one) from the host copies of ``tensors()``."""

    def read(self) -> list[dict[str, float]]:
        """The figures, one host sync: one dict per run (a single run's: one)."""
        return read_figures([self])[0]


def read_figures(batch: Sequence[Figures]) -> list[list[dict[str, float]]]:
    """Many updates' figures in one host read, in update order: each update's one dict per run. Raises
    ``FloatingPointError`` at the first update that ends a run (``MAX_NONFINITE_IN_A_ROW``)."""
    tensors = [t for figures in batch for t in figures.tensors()]
    if not tensors:
        return [figures.rows([]) for figures in batch]
    flat = torch.cat([t.detach().reshape(-1).float() for t in tensors])
    values = np.asarray(flat.cpu(), dtype=np.float64)  # the one host sync
    host = np.split(values, np.cumsum([t.numel() for t in tensors])[:-1])
    out, i = [], 0
    for figures in batch:
        n = len(figures.tensors())
        out.append(figures.rows(host[i : i + n]))
        i += n
    return out


@dataclass(frozen=True)
class StepFigures(Figures):
    """A :class:`NetworkAgent` update's figures: ``table [len(names) + 1, R]`` (a single run's R = 1), the figures
    as computed (a skipped run's loss and gradient norm too, for the failure's message) and, last, each run's count
    of non-finite updates in a row up to this one (> 0: this update was skipped, its loss and norm read as NaN)."""

    agent: str  # the algorithm's name, for the failure's message
    seeds: tuple[int, ...]
    names: tuple[str, ...]
    table: Tensor

    def tensors(self) -> list[Tensor]:
        return [self.table]

    def rows(self, host: list[np.ndarray]) -> list[dict[str, float]]:
        table = host[0].reshape(len(self.names) + 1, -1)
        streak = table[-1]
        worst = int(np.argmax(streak))
        if streak[worst] >= MAX_NONFINITE_IN_A_ROW:
            raise FloatingPointError(
                f"{self.agent} (run of seed {self.seeds[worst]}): {int(streak[worst])} updates in a row had a "
                f"non-finite loss ({table[0, worst]}) or gradient norm ({table[1, worst]}); the weights were kept as "
                "they were. Check the env's rewards and observations for NaN/inf, or lower lr"
            )
        rows = [dict(zip(self.names, col, strict=True)) for col in table[:-1].T.tolist()]
        for row, skipped in zip(rows, streak > 0, strict=True):
            if skipped:
                row.update(loss=float("nan"), grad_norm=float("nan"))
        return rows


class Agent(Protocol):
    """What the trainers, actors, evaluation and checkpoints call: every algorithm and the hierarchical wrapper,
    R ≥ 1 runs of it trained as one agent (a single run: R = 1)."""

    runs: int
    seeds: tuple[int, ...]  # run k's seed
    spec: EnvSpec
    device: torch.device
    progress: Progress
    updates: int
    chunk_len: int

    @property
    def cfg(self) -> AlgoConfig: ...  # read-only here, so an algorithm's own config class (MeSNConfig, …) fits
    @property
    def name(self) -> str: ...  # the registry's name (a class constant; the hierarchical wrapper's is per instance)
    def act(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput: ...
    def initial_state(self, num_envs: int) -> Any: ...
    def reset_state(self, state: Any, done: np.ndarray) -> Any: ...
    def observe(self, chunk: dict[str, np.ndarray]) -> None: ...
    def can_update(self) -> bool: ...
    def updates_for(self, n_transitions: int) -> float: ...
    def update(self) -> Figures: ...  # left on the device: ``read()`` them, one dict per run
    def policy_state(self) -> dict[str, Tensor]: ...
    def load_policy_state(self, state: dict[str, Tensor]) -> None: ...
    def state_dict(self) -> dict[str, Any]: ...
    def load_state_dict(self, state: dict[str, Any]) -> None: ...
    def n_parameters(self) -> int: ...
    def reserve_replay(self, env_steps: int) -> None: ...  # replay rows for at most ``env_steps`` (per run)
    def member(self, k: int) -> Agent: ...  # run k as the single run of its seed (evaluation, checkpoints)
    def load_member_state(self, k: int, state: dict[str, Any]) -> None: ...  # a single run's state into run k


# --- the shared pieces ---------------------------------------------------------------------------------------------
def decay_progress(cfg: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """How far the exploration schedule has run, 0 → 1 over min(fraction × run, max steps), then 1."""
    horizon = max(1, min(int(cfg.eps_decay_fraction * total_steps), cfg.eps_decay_max_steps))
    return min(1.0, env_steps / horizon)


def epsilon_at(cfg: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """Linear decay from ``eps_start`` to ``eps_end`` over min(fraction × run, max steps), then constant."""
    return cfg.eps_start + decay_progress(cfg, env_steps, total_steps) * (cfg.eps_end - cfg.eps_start)


def run_fraction(env_steps: int, total_steps: int) -> float:
    """How far the run has gone, 0 → 1 (held at 1 past its end)."""
    return min(1.0, env_steps / max(1, total_steps))


def lr_at(cfg: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """``lr`` annealed linearly to ``lr_end`` over the run (``lr`` throughout when ``lr_end`` is None)."""
    if cfg.lr_end is None:
        return cfg.lr
    return cfg.lr + run_fraction(env_steps, total_steps) * (cfg.lr_end - cfg.lr)


def epsilon_greedy(
    q: Tensor, epsilon: np.ndarray, mask: Tensor, n_actions: Tensor, stream: RunStreams
) -> tuple[np.ndarray, np.ndarray]:
    """(actions, greedy actions) ``[R, B, N]`` from Q ``[R, B, N, A]`` of R runs and ε per run and env ``[R, B]``;
    random actions stay within each agent's own action count (``mask`` ``[N, A]``, ``n_actions`` ``[N]``). A run
    whose ε is 0 draws no random number: greedy acting (an evaluation in the middle of training) leaves the
    exploration stream, and so the training run, as it was."""
    return explore(q.masked_fill(~mask, NEG).argmax(dim=-1), epsilon, n_actions, stream)


def explore(
    greedy: Tensor, epsilon: np.ndarray, n_actions: Tensor, stream: RunStreams
) -> tuple[np.ndarray, np.ndarray]:
    """``epsilon_greedy`` from the greedy actions ``[R, B, N]`` (on the device): one draw for every run, from each
    run's own stream, and one copy of the actions to the host."""
    drawing = epsilon.reshape(len(epsilon), -1).any(axis=1)  # [R]: the runs that explore at all
    if not drawing.any():
        greedy_np = greedy.cpu().numpy()
        return greedy_np, greedy_np
    advance = None if drawing.all() else torch.as_tensor(drawing, device=greedy.device).long()
    words = stream.bits((2, *greedy.shape[1:]), advance)  # [R, 2, B, N]: whether to explore, which action
    eps = torch.as_tensor(np.array(epsilon, dtype=np.float32), device=greedy.device).unsqueeze(-1)  # [R, B, 1]
    actions = torch.where(to_uniform(words[:, 0]) < eps, to_integers(words[:, 1], n_actions), greedy)
    both = torch.stack([actions, greedy]).cpu().numpy()
    return both[0], both[1]


def taken(q: Tensor, action: Tensor) -> Tensor:
    """Q of the actions taken: ``[..., N, A]`` → ``[..., N]``."""
    return q.gather(-1, action.unsqueeze(-1)).squeeze(-1)


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


@torch.no_grad()
def bootstrap_target(q_fn: QFn, online: nn.ModuleDict, target: nn.ModuleDict, batch: Batch, cfg: AlgoConfig,
                     mask: Tensor, gamma: float | Tensor | None = None,
                     alpha: float | Tensor | None = None) -> Tensor:  # fmt: skip
    """The TD target ``[M, N]`` of a batch for any ``q_fn``: the target networks' Q at the next observation, the
    action picked by the online networks (``double_q``), a per-sample ``discount`` when stored (options), and
    advantage learning's action gap ``max_b Q̄(s, b) − Q̄(s, a)`` subtracted when ``advantage_learning`` > 0.
    ``gamma`` and ``alpha`` override ``cfg.gamma`` and ``cfg.advantage_learning`` (a population's one per run:
    ``[R, 1]`` like a per-sample discount, ``[R, 1, 1]``)."""
    q_next_t = q_fn(target, batch["next_obs"])
    q_next_o = q_fn(online, batch["next_obs"]) if cfg.double_q else None
    discount = batch.get("discount", cfg.gamma if gamma is None else gamma)
    y = td_target(batch["reward"], batch["terminated"], discount, q_next_t, q_next_o, mask)
    alpha = cfg.advantage_learning if alpha is None else alpha
    if isinstance(alpha, Tensor) or alpha:
        q_now = q_fn(target, batch["obs"])
        gap = q_now.masked_fill(~mask, NEG).max(dim=-1).values - taken(q_now, batch["action"])
        y = y - alpha * gap
    return y


def n_step_rows(chunk: dict[str, np.ndarray], n: int, gamma: float | np.ndarray) -> dict[str, np.ndarray]:
    """A chunk ``[T, …]`` of one-step transitions as multi-step ones: step t's reward becomes
    ``Σ_k γ^k r_{t+k}`` over the m ≤ n steps up to the first that ended its episode or the chunk's last, its
    ``next_obs``, ``terminated`` and ``truncated`` those of step t+m−1, and ``discount = γ^m`` for the bootstrap
    (a per-sample discount, as an option's). ``gamma`` may be one per run, ``[R]`` for a population's
    ``[T, R, B, …]``. Chunks hold consecutive steps of the same envs, so no step's return reaches past them."""
    reward, done = chunk["reward"], chunk["terminated"] | chunk["truncated"]
    t_len, lead = reward.shape[0], done.shape[1:]
    g = np.asarray(gamma, dtype=np.float32).reshape(-1, *([1] * (len(lead) - 1))) if np.ndim(gamma) else gamma
    ret = np.zeros_like(reward)
    discount = np.ones((t_len, *lead), dtype=np.float32)  # γ^k of the next step to add, then γ^m
    steps = np.arange(t_len).reshape(-1, *([1] * len(lead)))
    last = np.zeros((t_len, *lead), dtype=np.int64)  # the step whose next_obs a row bootstraps from (k = 0 sets it)
    alive = np.ones((t_len, *lead), dtype=bool)  # no step before t+k ended the episode
    for k in range(min(n, t_len)):
        use = alive[: t_len - k]
        ret[: t_len - k] += np.where(use, discount[: t_len - k], 0.0)[..., None] * reward[k:]
        last[: t_len - k] = np.where(use, steps[k:], last[: t_len - k])
        discount[: t_len - k] = np.where(use, discount[: t_len - k] * g, discount[: t_len - k])
        alive[: t_len - k] &= ~done[k:]

    def at_last(v: np.ndarray) -> np.ndarray:
        idx = last.reshape(*last.shape, *([1] * (v.ndim - last.ndim)))
        return np.take_along_axis(v, idx, axis=0)

    return {**chunk, "reward": ret, "next_obs": at_last(chunk["next_obs"]), "terminated": at_last(chunk["terminated"]),
            "truncated": at_last(chunk["truncated"]), "discount": discount}  # fmt: skip


def td_loss(q: Tensor, y: Tensor, cfg: AlgoConfig) -> Tensor:
    """Elementwise TD loss: Huber (clipped error) or the paper's squared error, per the ``huber`` switch."""
    return F.smooth_l1_loss(q, y, reduction="none") if cfg.huber else 0.5 * (q - y) ** 2


def per_run(x: Tensor, like: Tensor) -> Tensor:
    """One value per run ``[R]`` shaped to broadcast over a stacked tensor ``like [R, …]`` (a 0-dim one as it is)."""
    return x if x.dim() == 0 else x.reshape(-1, *([1] * (like.dim() - 1)))


def polyak_(average: nn.Module, online: nn.Module, tau: float | Tensor) -> None:
    """average ← (1 − τ)·average + τ·online, in place (the Polyak target and the averaged policy). ``tau`` may be a
    device tensor, one weight per run ``[R]`` (or 0-dim): 0 leaves a run as it is and 1 copies it exactly (lerp
    computes ``online − (online − average)·(1 − τ)`` for τ ≥ 0.5), so it is also a masked copy with no host read."""
    avg: list[Tensor] = list(average.parameters())
    new: list[Tensor] = list(online.parameters())
    with torch.no_grad():
        if isinstance(tau, Tensor):
            torch._foreach_lerp_(avg, new, [per_run(tau, p) for p in avg])
        else:
            torch._foreach_lerp_(avg, new, tau)


# --- the plumbing every network agent shares -------------------------------------------------------------------------
class NetworkAgent(ABC):
    """Online and target networks (``build``), Adam, ε-greedy acting on ``greedy_q`` and one guarded gradient step
    of ``loss`` per ``update``. Subclasses say how they get their data (``observe``, ``can_update``,
    ``updates_for``, ``sample``)."""

    name: ClassVar[str]
    # steps per ``observe`` chunk the trainer should collect (DIAL: its unroll; n-step returns: 4·n, so that three
    # rows in four span all n steps — a return never reaches past its chunk)
    chunk_len: int = 1
    uses_messages: ClassVar[bool] = False
    # ``update`` syncs the targets every target_update updates; DIAL syncs by finished episodes instead and
    # behaviour cloning has no bootstrap target at all
    syncs_by_updates: ClassVar[bool] = True

    def __init__(
        self, spec: EnvSpec, cfg: AlgoConfig, device: str | torch.device = "auto", seed: int | Sequence[int] = 0
    ) -> None:
        """R runs, one per seed of ``seed`` (an int: a single run, R = 1), whose weights, optimizer state, replay
        and random streams carry a leading run axis, run k being the run of ``seed[k]`` (its initial weights,
        replay draws, exploration and message noise are that single run's), all updated by one batched step. It
        acts on ``[R, B, N, D]``, observes chunks ``[T, R, B, …]`` and its ``update`` reads as one dict of figures
        per run; a single run's caller may leave the run axis out of ``act``, ``observe`` and ``reset_state``."""
        model = ALGORITHMS[self.name].config
        if not isinstance(cfg, model):
            raise TypeError(f"{self.name} needs a {model.__name__}, got {type(cfg).__name__}")
        if cfg.hidden is None or cfg.share_params is None:
            raise ValueError("config: resolve env defaults first (convoy.config.resolve_algo)")
        self.spec, self.cfg = spec, cfg
        if cfg.n_step > 1:
            self.chunk_len = 4 * cfg.n_step
        self.device = pick_device(device) if isinstance(device, str) else device
        self.n_agents, self.obs_dim, self.n_act = spec.n_agents, spec.obs_dim, spec.max_actions
        self.shared: bool = bool(cfg.share_params)
        self.seeds = (int(seed),) if isinstance(seed, int | np.integer) else tuple(int(s) for s in seed)
        self.runs = len(self.seeds)  # a single run is a population of one
        if self.runs == 0:
            raise ValueError("seed: a population needs at least one seed")
        # the joint replay every step-based learner samples from, on the device: rows hold the declared transition
        # (and the act's extras), allocated on the first chunk
        declared = schema(self.n_agents, self.obs_dim)
        self.replay = JointReplay(cfg.replay_capacity, runs=self.runs, declared=declared, device=self.device)
        # explicit streams per run and purpose, on the device (``algos.streams``), never global state: replay draws,
        # exploration (and CoDBC's teacher share), noise (DIAL's DRU, Gumbel messages, a noisy channel control)
        self.streams = {name: RunStreams(self.seeds, name, self.device) for name in STREAMS}
        self.n_actions_np = np.asarray(spec.n_actions, dtype=np.int64)
        self.action_counts = torch.as_tensor(self.n_actions_np, device=self.device)  # [N]
        mask = torch.arange(self.n_act)[None, :] < torch.as_tensor(spec.n_actions)[:, None]
        self.action_mask = mask.to(self.device)  # [N, A]
        self.progress = Progress()
        self.updates = 0  # update() calls, a skipped one too (whether a run skipped is known on the device only)
        # on the device, so that no update reads them: updates with a run whose loss or gradient was not finite
        # (``skipped_updates``), and each run's count of them in a row (read with the figures)
        self._skipped = torch.zeros((), dtype=torch.int64, device=self.device)
        self._nonfinite_in_a_row = torch.zeros(self.runs, dtype=torch.int64, device=self.device)
        self._compiled: Callable[[Batch], tuple[tuple[str, ...], Tensor]] | None = None
        # Initial weights are a function of ``seed`` alone, not of whatever the caller's global RNG holds: a run
        # built without seeding torch first (a benchmark, a notebook) repeats, and the caller's stream is untouched.
        per_run = []
        for s in self.seeds:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(s)
                per_run.append(nn.ModuleDict(self.build()))
        self.online: nn.ModuleDict = stack_runs(per_run).to(self.device)
        self.target: nn.ModuleDict = copy.deepcopy(self.online)
        self.target.requires_grad_(False)
        # ``policy_ema`` < 1: the Polyak average of the online weights that evaluation acts with (``evaluated``)
        self.average: nn.ModuleDict | None = None
        if cfg.policy_ema < 1.0:
            self.average = copy.deepcopy(self.online)
            self.average.requires_grad_(False)
        self._optimizer: RunAdam | None = None
        self._members: dict[int, NetworkAgent] = {}
        self.run_cfgs: list[AlgoConfig] = [cfg] * len(self.seeds)
        self.gamma: float | Tensor = cfg.gamma
        self.alpha: float | Tensor = cfg.advantage_learning
        self._periods: Tensor | None = None  # each run's target_update [R], when they differ

    @property
    def skipped_updates(self) -> int:
        """Updates in which some run's loss or gradient was not finite (that run took no step); a host read."""
        return int(self._skipped)

    @skipped_updates.setter
    def skipped_updates(self, value: int) -> None:
        self._skipped.fill_(value)

    def set_run_configs(self, configs: Sequence[AlgoConfig]) -> None:
        """Give each run of a population its own hyper-parameters among ``PER_RUN`` (a grid over seeds × lr × γ ×
        target period × ε schedule in one population); every other field must agree, since it sets shapes or the
        update's structure."""
        if len(configs) != self.runs:
            raise ValueError(f"configs: one per run of the population ({self.runs}), got {len(configs)}")
        base = configs[0].model_dump()
        for cfg in configs[1:]:
            if type(cfg) is not type(configs[0]):
                raise ValueError(
                    f"configs: one algorithm's configs, got {type(cfg).__name__} beside {type(configs[0]).__name__}"
                )
            for name, value in cfg.model_dump().items():
                if name not in PER_RUN and value != base[name]:
                    raise ValueError(
                        f"{name}: runs of one population must share it ({base[name]!r} vs {value!r}); only "
                        f"{', '.join(PER_RUN)} may differ per run"
                    )
        if self._optimizer is not None:
            raise RuntimeError("set_run_configs: call it before the first update")
        self.run_cfgs, self.cfg = list(configs), configs[0]
        gammas, alphas = [c.gamma for c in configs], [c.advantage_learning for c in configs]
        self.gamma = gammas[0] if len(set(gammas)) == 1 else torch.tensor(gammas, device=self.device).reshape(-1, 1)
        self.alpha = alphas[0] if len(set(alphas)) == 1 else torch.tensor(alphas, device=self.device).reshape(-1, 1, 1)
        periods = [c.target_update for c in configs]
        self._periods = None if len(set(periods)) == 1 else torch.tensor(periods, device=self.device)

    @property
    def optimizer(self) -> RunAdam:
        """Adam with one learning rate per run on the device (:class:`RunAdam`), made on first use: actors never
        update, and the first optimizer of a process costs ~2 s of imports."""
        if self._optimizer is None:
            lrs = torch.tensor([c.lr for c in self.run_cfgs], device=self.device)
            ends = torch.tensor([lr_at(c, 1, 1) for c in self.run_cfgs], device=self.device)  # at the run's end
            self._optimizer = RunAdam(list(self.online.parameters()), lrs, ends)
        return self._optimizer

    def anneal_lr(self) -> None:
        """Set each run's learning rate for where training stands (``lr_end``): one op on the device, from the
        host's progress; a no-op at constant lr."""
        if any(c.lr_end is not None for c in self.run_cfgs):
            p = self.progress
            self.optimizer.anneal(run_fraction(p.env_steps, p.total_steps))

    # --- what each algorithm writes ------------------------------------------------------------------------------
    @abstractmethod
    def build(self) -> dict[str, nn.Module]:
        """The online networks by name (targets are deep copies)."""

    @abstractmethod
    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor | None, Any]:
        """Execution-mode Q-values ``[B, N, A]``, messages sent (or None) and the next recurrent state."""

    @abstractmethod
    def loss(self, batch: Batch) -> Loss:
        """The batch's loss, in the order of the algorithm's paper."""

    # --- data: the joint replay (DIAL brings its own sequences) ------------------------------------------------
    def observe(self, chunk: dict[str, np.ndarray], valid: np.ndarray | None = None) -> None:
        """Chunks ``[T, R, B, …]`` (a single run's may leave out its run axis, ``[T, B, …]``) as rows in time-major
        order, per run; ``valid [T, R, B]`` keeps only those rows (each run's meta-transitions, in hierarchical
        DQN). With ``n_step`` > 1 the rows are multi-step transitions (``n_step_rows``)."""
        chunk = with_run_axis(chunk, self.runs)
        if self.cfg.n_step > 1:
            gamma = self.gamma.cpu().numpy().reshape(-1) if isinstance(self.gamma, Tensor) else self.gamma
            chunk = n_step_rows(chunk, self.cfg.n_step, gamma)
        runs = {k: v.swapaxes(0, 1).reshape(self.runs, -1, *v.shape[3:]) for k, v in chunk.items()}
        if valid is not None:
            valid = valid.reshape(len(valid), self.runs, -1).swapaxes(0, 1).reshape(self.runs, -1)
        self.replay.add(runs, valid)

    def reserve_replay(self, env_steps: int) -> None:
        """Allocate replay for a run that observes at most ``env_steps`` joint env steps (summed over its envs),
        not for all of ``replay_capacity``: one row per env step (an n-step row too), so ``env_steps`` rows."""
        self.replay.reserve(max(1, env_steps))

    def can_update(self) -> bool:
        """Whether the replay holds enough transitions to learn from."""
        return len(self.replay) >= max(self.cfg.learning_starts, self.cfg.batch_size)

    def updates_for(self, n_transitions: int) -> float:
        """Updates owed for ``n_transitions`` newly observed joint transitions: ``replay_ratio`` samples each."""
        return n_transitions * self.cfg.replay_ratio / self.cfg.batch_size

    def sample(self) -> Batch:
        """The next training batch (``batch_size`` joint transitions, each run's from its own replay), drawn and
        gathered on the device."""
        return self.replay.sample(self.cfg.batch_size, self.streams["replay"])

    # --- acting --------------------------------------------------------------------------------------------------
    def initial_state(self, num_envs: int) -> Any:
        """Recurrent state for ``num_envs`` fresh envs per run, ``[R, B, …]`` (None for feed-forward algorithms)."""
        return None

    def reset_state(self, state: Any, done: np.ndarray) -> Any:
        """Clear the recurrent state of envs whose episode just ended (``done [R, B]``, a single run's ``[B]``)."""
        return self.reset_runs(state, np.asarray(done, dtype=bool).reshape(self.runs, -1))

    def reset_runs(self, state: Any, done: np.ndarray) -> Any:
        """``reset_state`` with ``done [R, B]``."""
        return state

    def extras(self, obs: np.ndarray, state: Any = None) -> dict[str, np.ndarray]:
        """Per-env arrays to store with each transition (a fingerprint, an observation history), given the
        observations and the recurrent state after this act; none by default."""
        return {}

    def rand_like(self, x: Tensor, normal: bool = False) -> Tensor:
        """Noise shaped like ``x [R, …]`` (uniform in [0, 1), or standard normal) from each run's own noise stream,
        one draw for all runs: run k draws exactly what the single run of its seed draws."""
        stream = self.streams["noise"]
        return stream.normal(x.shape[1:], x.dtype) if normal else stream.uniform(x.shape[1:], x.dtype)

    def explore(self, q: Tensor, epsilon: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``epsilon_greedy`` for this agent on Q ``[R, B, N, A]``, one greedy pass and one draw for every run (ε a
        scalar, one per run ``[R]`` or per run and env ``[R, B]``; a single run's may be one per env ``[B]``): the
        actions, the greedy actions and ε per env and agent, ``[R, B, N]``."""
        eps = np.asarray(epsilon, dtype=np.float64)
        eps = np.broadcast_to(eps.reshape(self.runs, -1) if eps.ndim else eps, q.shape[:2])  # [R, B]
        actions, greedy = epsilon_greedy(q, eps, self.action_mask, self.action_counts, self.streams["explore"])
        return actions, greedy, np.broadcast_to(eps[..., None], actions.shape)

    def sync_targets(self) -> None:
        """After an update: copy the online weights into the target of every run whose ``target_update`` period
        the update count has reached. The count is the host's, so this ``if`` reads nothing from the device and
        stays outside the compiled step; runs with their own periods are picked by a 0/1 mask made on the device.
        Polyak targets (``target_tau`` < 1) move in the step itself."""
        if self.cfg.target_tau < 1.0 or not any(self.updates % c.target_update == 0 for c in self.run_cfgs):
            return
        if self._periods is None:  # every run is due
            with torch.no_grad():
                torch._foreach_copy_(list(self.target.parameters()), list(self.online.parameters()))
        else:
            polyak_(self.target, self.online, (torch.remainder(self.updates, self._periods) == 0).float())

    def sync_runs(self, due: np.ndarray) -> None:
        """Copy the online weights into the target of the runs ``due`` (runs that sync apart, DIAL's)."""
        idx = torch.as_tensor(np.flatnonzero(due), device=self.device)
        with torch.no_grad():
            for t, o in zip(self.target.parameters(), self.online.parameters(), strict=True):
                t.index_copy_(0, idx, o.index_select(0, idx))

    @property
    def evaluated(self) -> nn.ModuleDict:
        """The weights a policy is judged by: the online ones, or their average when ``policy_ema`` < 1."""
        return self.online if self.average is None else self.average

    def act(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput:
        """ε-greedy actions for ``obs [R, B, N, D]``, ε a scalar, one per run ``[R]`` or one per run and env ``[R, B]``
        (Ape-X style). A single run may leave out its run axis, ``[B, N, D]`` with ε a scalar or one per env
        ``[B]``: what comes back has the caller's leading dims (``ActOutput.shaped``)."""
        runs = np.reshape(obs, (self.runs, -1, *np.shape(obs)[-2:]))
        return self.act_runs(runs, epsilon, state).shaped(np.shape(obs)[:-2])

    @torch.no_grad()
    def act_runs(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput:
        """``act`` on ``obs [R, B, N, D]``. Outside training (``progress.training`` off: evaluation, a loaded
        checkpoint) it acts with ``evaluated``."""
        obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
        if self.progress.training or self.average is None:
            q, msgs, new_state = self.greedy_q(obs_t, state)
        else:  # every algorithm's greedy_q reads self.online: lend it the average for this call
            online, self.online = self.online, self.average
            try:
                q, msgs, new_state = self.greedy_q(obs_t, state)
            finally:
                self.online = online
        actions, _, _ = self.explore(q, epsilon)
        return ActOutput(
            actions=actions,
            messages=None if msgs is None else msgs.cpu().numpy(),
            extras=self.extras(obs, new_state),
            state=new_state,
        )

    # --- learning ------------------------------------------------------------------------------------------------
    def bootstrap(self, q_fn: QFn, batch: Batch) -> Tensor:
        """``bootstrap_target`` with this agent's networks, config and (a population's per-run) γ and α."""
        return bootstrap_target(
            q_fn, self.online, self.target, batch, self.cfg, self.action_mask, self.gamma, self.alpha
        )

    def agent_losses(self, batch: Batch) -> Tensor:
        """Each run's agents' losses ``[R, N]`` on ``batch`` (tests back-propagate one to see which weights it
        reaches)."""
        return self.loss(batch).agents

    def update(self) -> Figures:
        """One gradient step on a sampled batch (the agents' losses summed, plus any auxiliary term), then the
        target sync; the figures stay on the device (``Figures``: ``read()`` them, or let the trainer read them in
        batches). Nothing in the update waits for the device: a non-finite loss or gradient is caught by a mask
        on the device and never reaches the weights, and the run fails (``FloatingPointError``) when figures that
        counted ``MAX_NONFINITE_IN_A_ROW`` such updates in a row are read, so at most one read interval late
        (``READ_EVERY`` updates in the trainer).

        A population takes one step for all runs: their losses are summed (no weight is shared between runs, so
        each run's gradient is its own loss's), each run's gradient is clipped to its own norm, and a run whose
        loss or gradient is not finite keeps its weights, target, Adam moments and step count while the others
        step. ``updates`` counts every call, skipped or not: the host cannot know without a read. With ``compile``
        the step from the batch on runs as one captured graph (``torch.compile(fullgraph=True)``).
        """
        batch = self.sample()
        self.anneal_lr()
        names, table = self._compiled_step(batch) if self.cfg.compile else self._step(batch)
        self.updates += 1
        if self.syncs_by_updates:
            self.sync_targets()
        return StepFigures(self.name, self.seeds, names, table)

    def _compiled_step(self, batch: Batch) -> tuple[tuple[str, ...], Tensor]:
        """``_step`` compiled whole on first use (no graph break: a break is an error). On CUDA the graph is also
        captured as a CUDA graph (``cuda_graph_options``): one launch per update instead of one per kernel.
        A CUDA graph replays fixed addresses, so the state the step writes in place (Adam's moments and counts, the
        learning rates, the guard's counters, the noise streams' counters) is marked static, and the figures are
        copied out: the next replay overwrites its outputs, and figures are read many updates later."""
        cuda = self.device.type == "cuda"
        if self._compiled is None:
            opt = self.optimizer  # made before tracing: its state is the graph's input, not built in it
            if cuda:
                mutated = [*opt._m, *opt._v, opt._steps, opt.lrs, self._skipped, self._nonfinite_in_a_row]
                for t in mutated + [s.counters for s in self.streams.values()]:
                    torch._dynamo.mark_static_address(t)
            self._compiled = torch.compile(self._step, fullgraph=True, options=cuda_graph_options() if cuda else None)
        with torch._dynamo.config.patch(trace_autograd_ops=True):  # autograd.grad inside the graph
            names, table = self._compiled(batch)
        return names, table.clone() if cuda else table

    def _step(self, batch: Batch) -> tuple[tuple[str, ...], Tensor]:
        """Loss → gradients → each run's clip → the non-finite guard → Adam → Polyak target and policy average,
        all on the device. Returns the figures' names and their table (``StepFigures``)."""
        out = self.loss(batch)
        loss = out.agents.sum(dim=-1)  # [] or [R]
        total = loss.sum() if out.extra is None else loss.sum() + out.extra.sum()
        params = self.optimizer.params
        raw = torch.autograd.grad(total, params, allow_unused=True)
        # a weight no loss reaches (a cut channel's message net) gets a zero gradient: Adam then leaves it as it is
        grads = [torch.zeros_like(p) if g is None else g.contiguous() for p, g in zip(params, raw, strict=True)]
        grad_norm = clip_grad_norm_per_run(grads, self.cfg.grad_clip)
        ok = torch.isfinite(loss) & torch.isfinite(grad_norm)  # [] or [R]: which runs step
        self.optimizer.step_runs(grads, ok)
        with torch.no_grad():
            skipped = ~ok
            self._skipped.add_(skipped.any())
            self._nonfinite_in_a_row.add_(1).mul_(skipped)
            if self.syncs_by_updates and self.cfg.target_tau < 1.0:
                polyak_(self.target, self.online, self.cfg.target_tau * ok.float())
            if self.average is not None:
                polyak_(self.average, self.online, self.cfg.policy_ema * ok.float())
            # a figure given as a float is filled in on the device (a tensor made from it would be a host copy)
            stats = [v.float().expand_as(loss) if isinstance(v, Tensor) else torch.full_like(loss, v)
                     for v in out.stats.values()]  # fmt: skip
            table = torch.stack([loss.detach(), grad_norm, *stats, self._nonfinite_in_a_row.float()])
        return ("loss", "grad_norm", *out.stats), table.reshape(table.shape[0], -1)

    def sync_target(self) -> None:
        self.target.load_state_dict(self.online.state_dict())

    # --- persistence ---------------------------------------------------------------------------------------------
    def policy_state(self) -> dict[str, Tensor]:
        """What an actor needs to act: the online weights (on CPU, for the wire or a file)."""
        return {k: v.detach().cpu() for k, v in self.online.state_dict().items()}

    def load_policy_state(self, state: dict[str, Tensor]) -> None:
        """Act with ``state`` (an actor's weights from the learner): in training and out of it."""
        self.online.load_state_dict(state)
        if self.average is not None:
            self.average.load_state_dict(state)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume learning exactly: networks, targets, optimizer, counters, random streams —
        a single run's, in the layout its checkpoints have always had (no run axis): ``run_state_dict(0)``."""
        if self.runs != 1:
            raise TypeError("a population's state is saved per run: member(k).state_dict()")
        return self.run_state_dict(0)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """A single run's state (``state_dict``, a checkpoint's) into a run of one: ``load_member_state(0, …)``."""
        if self.runs != 1:
            raise TypeError("a population loads a single run's state per run: load_member_state(k, state)")
        self.load_member_state(0, state)

    def run_state_dict(self, k: int) -> dict[str, Any]:
        """Run k's state as a single run's ``state_dict``: every tensor without the run axis."""
        opt = self.optimizer.state_dict()
        moments = {i: {n: v[k].clone() for n, v in st.items()} for i, st in opt["state"].items()}  # step: run k's
        return {
            "online": run_state(self.online, k),
            "target": run_state(self.target, k),
            **({} if self.average is None else {"average": run_state(self.average, k)}),
            "optimizer": {"param_groups": opt["param_groups"], "state": moments},
            "updates": self.updates,
            "streams": self.stream_state(k),
            **self.member_state(k),
        }

    def stream_state(self, k: int) -> dict[str, int]:
        """Run k's random streams: the seed they are keyed by and each purpose's counter (``algos.streams``)."""
        streams = self.streams.values()
        return {"seed": next(iter(streams)).seeds[k], **{s.stream: s.state(k) for s in streams}}

    def load_streams(self, k: int, state: dict[str, Any]) -> None:
        """Run k's streams from a single run's state. A checkpoint written before the device streams holds numpy
        and torch generator states instead ("rng", "torch_rng", DIAL's "dru_rng"): its streams start at
        ``legacy_counter(seed, updates)``, so such a resumed run draws other numbers than the old code would have
        (another generator), though the same ones at every resume of that file."""
        saved = state.get("streams")
        for name, stream in self.streams.items():
            if saved is None:
                stream.load(k, legacy_counter(stream.seeds[k], int(state["updates"])))
            else:
                stream.load(k, saved[name], saved["seed"])

    # --- a population's runs as single runs ------------------------------------------------------------------------
    def member(self, k: int) -> NetworkAgent:
        """Run k of a population as a single-run agent of its seed holding the run's current state (weights,
        targets, optimizer, counters, random streams): what evaluation and checkpoints of that run use. The
        replay stays with the population. A run of one is its own member."""
        if self.runs == 1:
            return self
        agent = self._members.get(k)
        if agent is None:
            agent = self._members[k] = type(self)(self.spec, self.run_cfgs[k], device=self.device, seed=self.seeds[k])
        agent.load_state_dict(self.run_state_dict(k))
        p = self.progress
        episodes = int(np.broadcast_to(p.episodes, (self.runs,))[k])  # one count for all runs, or one per run
        agent.progress = Progress(p.env_steps, episodes, p.total_steps, p.training)
        agent.skipped_updates = self.skipped_updates
        return agent

    def member_state(self, k: int) -> dict[str, Any]:
        """What an algorithm adds to run k's ``state_dict`` beyond the networks, optimizer and streams."""
        return {}

    def load_member_state(self, k: int, state: dict[str, Any]) -> None:
        """Put a single run's state (``member(k).state_dict()``, a checkpoint's: no run axis) into run k: how a
        run resumes from its checkpoint, and a population from its runs'."""
        opt = self.optimizer
        with torch.no_grad():
            modules = [(self.online, "online"), (self.target, "target")]
            if self.average is not None:
                modules.append((self.average, "average" if "average" in state else "online"))
            for module, key in modules:
                for name, value in module.state_dict().items():
                    value[k].copy_(state[key][name])
            for i, st in state["optimizer"]["state"].items():  # a single run's Adam state (torch.optim.Adam's too)
                for n, v in st.items():
                    opt.state[opt.params[int(i)]][n][k].copy_(v)
        self.updates = int(state["updates"])
        self.load_streams(k, state)
        self.load_member_extra(k, state)

    def load_member_extra(self, k: int, state: dict[str, Any]) -> None:
        """Run k's share of what ``member_state`` adds, from a single run's state (nothing, unless it adds)."""
        return None

    def n_parameters(self) -> int:
        """Parameters of one run."""
        return sum(p.numel() for p in self.online.parameters()) // len(self.seeds)


# Hyper-parameters that may differ between the runs of one population: none changes a shape or the update's structure.
PER_RUN: tuple[str, ...] = (
    "lr", "lr_end", "gamma", "target_update", "advantage_learning", "eps_start", "eps_end", "eps_decay_fraction",
    "eps_decay_max_steps",
)  # fmt: skip


class RunAdam(torch.optim.Optimizer):
    """Adam (torch's defaults: β = (0.9, 0.999), ε = 1e-8) over R ≥ 1 runs' stacked parameters ``[R, …]``,
    with one learning rate per run on the device (``lrs``, annealed there) and a per-run ``ok`` mask
    (``step_runs``): a run not ok keeps its weights, moments and step count, with no host read.

    Its state has ``torch.optim.Adam``'s layout, ``step``, ``exp_avg`` and ``exp_avg_sq`` per parameter, made up
    front (a compiled step never branches on it), with a leading run axis (``step`` one count per run ``[R]``): a
    run's share is a single run's state, and a single run's, or a checkpoint that ``torch.optim.Adam(fused=True)``
    wrote, loads into a run (``NetworkAgent.load_member_state``). Every parameter steps at every update (one a loss
    does not reach with a zero gradient), so all of them share one ``step`` tensor.

    Two kernels, one arithmetic (equal to ``torch.optim.Adam`` up to float rounding): a run of one steps with
    torch's fused Adam, one kernel whose ``found_inf`` skips the step on the device; R > 1 runs, and any step
    under ``torch.compile``, with ``torch._foreach_*`` ops whose per-run factors mask the step — the fused kernel
    takes one learning rate and one skip flag per call, so per-run ones would cost a call per run.
    """

    def __init__(
        self,
        params: list[Tensor],
        lrs: Tensor,
        ends: Tensor | None = None,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        super().__init__(params, {"lr": 0.0, "betas": betas, "eps": eps})  # the rates live in ``lrs``
        self.params: list[Tensor] = list(params)
        self.runs = len(lrs)
        self.lrs, self.start = lrs, lrs.clone()
        self.span = torch.zeros_like(lrs) if ends is None else ends - lrs  # to each run's ``lr_end`` by the run's end
        self._fill_state()

    def _fill_state(self) -> None:
        """Zero moments for every parameter without them, and one shared step count (the largest loaded)."""
        shape = (self.runs,)
        device = self.params[0].device
        counts = [self.state[p]["step"] for p in self.params if "step" in self.state[p]]
        step = torch.zeros(shape, dtype=torch.float32, device=device)
        if counts:
            step = torch.stack([c.to(device=device, dtype=torch.float32).reshape(shape) for c in counts]).amax(0)
        for p in self.params:
            st = self.state[p]
            st["step"] = step
            for name in ("exp_avg", "exp_avg_sq"):
                if name not in st:
                    st[name] = torch.zeros_like(p, memory_format=torch.preserve_format)
        self._steps = step
        self._m = [self.state[p]["exp_avg"] for p in self.params]
        self._v = [self.state[p]["exp_avg_sq"] for p in self.params]

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self._fill_state()

    def anneal(self, fraction: float) -> None:
        """Each run's rate ``fraction`` of the way to its end rate, computed on the device (no host copy)."""
        torch.add(self.start, self.span, alpha=fraction, out=self.lrs)

    @overload
    def step(self, closure: None = None) -> None: ...
    @overload
    def step(self, closure: Callable[[], float]) -> float: ...
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # the closure is never called
        """``torch.optim``'s step: every run, from the parameters' ``.grad``."""
        grads = [torch.zeros_like(p) if p.grad is None else p.grad for p in self.params]
        self.step_runs(grads, torch.ones_like(self._steps, dtype=torch.bool))
        return None

    @torch.no_grad()
    def step_runs(self, grads: Sequence[Tensor], ok: Tensor) -> None:
        """One Adam step of the runs with ``ok`` (``[R]``, or 0-dim for a single run) from ``grads`` (parameter
        order, used as scratch: a run not ok may hold NaN there)."""
        b1, b2 = self.defaults["betas"]
        eps: float = self.defaults["eps"]
        okf = ok.float()
        self._steps.add_(okf)
        params, m, v = self.params, self._m, self._v
        if self.runs == 1 and not torch.compiler.is_compiling():  # one run: torch's fused kernel, its rounding
            steps = self._steps.view(())
            torch._fused_adam_(params, list(grads), m, v, [], [steps] * len(params), lr=self.lrs.view(()),
                               beta1=b1, beta2=b2, weight_decay=0.0, eps=eps, amsgrad=False, maximize=False,
                               found_inf=(1.0 - okf).view(()))  # fmt: skip
            return

        def each(x: Tensor) -> list[Tensor]:  # one value per run, for every parameter
            return [per_run(x, p) for p in params]

        grads = list(grads)
        for g, bad in zip(grads, each(~ok), strict=True):
            g.masked_fill_(bad, 0.0)  # NaN·0 is NaN: a skipped run's gradient must go, not be scaled
        # m ← m + (1 − β1)(g − m), v ← β2·v + (1 − β2)·g², as the fused kernel rounds them; unchanged where not ok
        torch._foreach_lerp_(m, grads, each(torch.where(ok, 1 - b1, 0.0)))
        torch._foreach_mul_(v, each(torch.where(ok, b2, 1.0)))
        torch._foreach_addcmul_(v, grads, grads, value=1 - b2)
        # bias corrections in float64, as torch's kernels take them (1 − 0.999 in float32 is off by 6e-5); a run
        # never stepped counts 0, clamped: any correction will do, it moves by 0
        t = self._steps.double().clamp(min=1.0)
        bias1, bias2 = 1 - b1**t, (1 - b2**t).sqrt()
        size = self.lrs.double() * bias2 / bias1  # Δp = −size · m / (√v + ε·bias2), torch's step rearranged
        # the denominator over ``size``, in the gradients' memory: ∞ for a run not ok, whose step is then m / ∞ = 0
        scale = torch.where(ok, 1 / size, 0.0).float()
        offset = torch.where(ok, eps * bias2 / size, math.inf).float()
        for g, sq in zip(grads, v, strict=True):
            torch.sqrt(sq, out=g)
        torch._foreach_mul_(grads, each(scale))
        torch._foreach_add_(grads, each(offset))
        torch._foreach_addcdiv_(params, m, grads, value=-1.0)


def clip_grad_norm_per_run(grads: list[Tensor], max_norm: float) -> Tensor:
    """Each run's gradient ``[R, …]`` scaled in place to at most ``max_norm`` (``clip_grad_norm_`` per run); the
    norms before the clip ``[R]``. One run's norm is summed as ``clip_grad_norm_`` sums it, bit for bit."""
    if grads[0].shape[0] == 1:
        total: Tensor = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads))).reshape(1)
    else:
        norms = torch.stack([torch.linalg.vector_norm(g.flatten(1), dim=1) for g in grads])  # [params, R]
        total = torch.linalg.vector_norm(norms, dim=0)  # [R]
    coef = (max_norm / (total + 1e-6)).clamp(max=1.0)
    torch._foreach_mul_(grads, [per_run(coef, g) for g in grads])
    return total
