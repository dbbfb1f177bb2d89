"""What the algorithms share besides their update: the agent protocol trainers and actors drive, and the base of
every network agent — its networks, how it acts (ε-greedy on ``greedy_q``) and how it gathers its data (the joint
replay every step-based learner samples from).

Each algorithm file reads top to bottom beside its paper: its networks (``build``), how it acts (``greedy_q``)
and its ``loss(batch)`` written out in Algorithm 1's order. :class:`NetworkAgent` holds what no algorithm file
should repeat: online and target networks for R ≥ 1 runs, ε-greedy ``act``, ``observe``/``sample`` and the
checkpoint layout; its ``update`` is the updater's (``algos/updater.py``: the loss's shared pieces and the guarded
step). DIAL learns from sequences and overrides the data path; hierarchical DQN wraps two agents; both fit
:class:`Agent`.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Protocol

import numpy as np
import torch
from torch import Tensor, nn

from convoy.algos.nets import pick_device, stack_runs
from convoy.algos.replay import JointReplay
from convoy.algos.streams import STREAMS, RunStreams, to_integers, to_uniform
from convoy.algos.updater import NEG, Batch, Figures, Loss, Updater, large_margin, run_fraction
from convoy.config import ALGORITHMS, AlgoConfig, DemonstrationFields
from convoy.envs.batched import EnvSpec
from convoy.transition import Transition, schema

PRIORITY_FLOOR = 1e-3  # added to |δ| before prioritized replay's exponent: no row stops being drawn


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


def with_run_axis(chunk: Transition[np.ndarray], runs: int) -> Transition[np.ndarray]:
    """A chunk ``[T, R, B, …]`` as it is, or a single run's ``[T, B, …]`` with its run axis put in (the leading
    dims read from ``terminated``, ``[T, B]`` or ``[T, R, B]``)."""
    lead = np.ndim(chunk.terminated)
    return chunk.map(lambda v: np.reshape(v, (np.shape(v)[0], runs, -1, *np.shape(v)[lead:])))


class Agent(Protocol):
    """What the trainers, actors, evaluation and checkpoints call: every algorithm and the hierarchical wrapper,
    R ≥ 1 runs of it trained as one agent (a single run: R = 1)."""

    runs: int
    seeds: tuple[int, ...]  # run k's seed
    spec: EnvSpec
    device: torch.device
    progress: Progress
    chunk_len: int

    @property
    def cfg(self) -> AlgoConfig: ...  # read-only here, so an algorithm's own config class (MeSNConfig, …) fits
    @property
    def name(self) -> str: ...  # the registry's name (a class constant; the hierarchical wrapper's is per instance)
    @property
    def updates(self) -> int: ...  # update() calls so far
    def act(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: Any = None) -> ActOutput: ...
    def initial_state(self, num_envs: int) -> Any: ...
    def reset_state(self, state: Any, done: np.ndarray) -> Any: ...
    def observe(self, chunk: Transition[np.ndarray]) -> None: ...
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


def epsilon_greedy(
    q: Tensor, epsilon: np.ndarray, mask: Tensor, n_actions: Tensor, stream: RunStreams, hold: Hold | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(actions, greedy actions) ``[R, B, N]`` from Q ``[R, B, N, A]`` of R runs and ε per run and env ``[R, B]``;
    random actions stay within each agent's own action count (``mask`` ``[N, A]``, ``n_actions`` ``[N]``). A run
    whose ε is 0 draws no random number: greedy acting (an evaluation in the middle of training) leaves the
    exploration stream, and so the training run, as it was. ``hold``: εz-greedy (``Hold``)."""
    return explore(q.masked_fill(~mask, NEG).argmax(dim=-1), epsilon, n_actions, stream, hold)


@dataclass
class Hold:
    """εz-greedy's state (Dabney et al. 2021, "Temporally-extended ε-greedy exploration"): an agent that explores
    repeats its random action for n steps, n drawn from a zeta distribution P(n) ∝ n^−μ on 1 … n_max, so that
    exploration can carry a car somewhere its greedy policy never goes, where one-step dithering averages out.
    ``action`` and ``left`` (steps still to repeat) per run, env and agent ``[R, B, N]``; ``cdf`` the durations'
    cumulative distribution ``[n_max]``. It belongs to the acting loop's envs, like their episodes: a checkpoint
    does not keep it, and a batch of another shape starts with no hold."""

    cdf: Tensor
    action: Tensor | None = None
    left: Tensor | None = None

    @classmethod
    def zeta(cls, mu: float, n_max: int, device: torch.device) -> Hold:
        p = torch.arange(1, n_max + 1, dtype=torch.float64) ** -mu
        return cls(cdf=(p.cumsum(0) / p.sum()).to(torch.float32).to(device))

    def durations(self, u: Tensor) -> Tensor:
        """Hold lengths 1 … n_max for uniforms ``u`` in [0, 1) (inverse CDF)."""
        return (torch.searchsorted(self.cdf, u.contiguous(), right=True) + 1).clamp(max=len(self.cdf))


def explore(
    greedy: Tensor, epsilon: np.ndarray, n_actions: Tensor, stream: RunStreams, hold: Hold | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``epsilon_greedy`` from the greedy actions ``[R, B, N]`` (on the device): one draw for every run, from each
    run's own stream, and one copy of the actions to the host. With ``hold`` an agent in the middle of a hold
    repeats its action; any other explores with probability ε and holds for a drawn length (env rows whose ε is 0
    act greedily and leave their holds as they are)."""
    drawing = epsilon.reshape(len(epsilon), -1).any(axis=1)  # [R]: the runs that explore at all
    if not drawing.any():
        greedy_np = greedy.cpu().numpy()
        return greedy_np, greedy_np
    advance = None if drawing.all() else torch.as_tensor(drawing, device=greedy.device).long()
    words = stream.bits((2 if hold is None else 3, *greedy.shape[1:]), advance)  # [R, 2|3, B, N]
    eps = torch.as_tensor(np.array(epsilon, dtype=np.float32), device=greedy.device).unsqueeze(-1)  # [R, B, 1]
    explores = to_uniform(words[:, 0]) < eps
    randoms = to_integers(words[:, 1], n_actions)
    if hold is None:
        actions = torch.where(explores, randoms, greedy)
    else:
        if hold.left is None or hold.left.shape != greedy.shape:
            hold.action, hold.left = torch.zeros_like(greedy), torch.zeros_like(greedy)
        assert hold.action is not None
        holding = (hold.left > 0) & (eps > 0)
        starts = ~holding & explores
        actions = torch.where(holding, hold.action, torch.where(starts, randoms, greedy))
        hold.action = torch.where(starts, randoms, hold.action)
        hold.left = torch.where(holding, hold.left - 1, torch.where(starts, hold.durations(to_uniform(words[:, 2])) - 1,
                                                                       hold.left))  # fmt: skip
    both = torch.stack([actions, greedy]).cpu().numpy()
    return both[0], both[1]


def n_step_rows(chunk: Transition[np.ndarray], n: int, gamma: float | np.ndarray) -> Transition[np.ndarray]:
    """A chunk ``[T, …]`` of one-step transitions as multi-step ones: step t's reward becomes
    ``Σ_k γ^k r_{t+k}`` over the m ≤ n steps up to the first that ended its episode or the chunk's last, its
    ``next_obs``, ``terminated`` and ``truncated`` those of step t+m−1, and ``discount = γ^m`` for the bootstrap
    (a per-sample discount, as an option's). ``gamma`` may be one per run, ``[R]`` for a population's
    ``[T, R, B, …]``. Chunks hold consecutive steps of the same envs, so no step's return reaches past them."""
    reward, done = chunk.reward, chunk.terminated | chunk.truncated
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

    return replace(chunk, reward=ret, next_obs=at_last(chunk.next_obs), terminated=at_last(chunk.terminated),
                   truncated=at_last(chunk.truncated), extras={**chunk.extras, "discount": discount})  # fmt: skip


# --- the plumbing every network agent shares -------------------------------------------------------------------------
class NetworkAgent(ABC):
    """Online and target networks (``build``), ε-greedy acting on ``greedy_q``, the joint replay, and one guarded
    gradient step of ``loss`` per ``update`` (``updater``). Subclasses may say otherwise how they get their data
    (``observe``, ``can_update``, ``updates_for``, ``sample``)."""

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
        # prioritized replay where the algorithm has it (independent DQN's ``priority_alpha``; its loss weighs and
        # returns priorities): the rows last drawn wait in ``_drawn`` for the update's |δ|
        self.priority_alpha: float = getattr(cfg, "priority_alpha", 0.0)
        self._drawn: Tensor | None = None
        self.replay = JointReplay(cfg.replay_capacity, runs=self.runs, declared=declared, device=self.device,
                                  prioritized=self.priority_alpha > 0)  # fmt: skip
        # ``demo_margin``: a second buffer, of each run's DAgger states and the teacher's actions there, sampled
        # beside the replay for DQfD's margin (``keep_demonstrations``, ``objective``)
        self.demo_margin: float = cfg.demo_margin if isinstance(cfg, DemonstrationFields) else 0.0
        self.demos: JointReplay | None = None
        if isinstance(cfg, DemonstrationFields) and self.demo_margin > 0:
            most = cfg.demo_rounds * cfg.demo_episodes * spec.max_steps  # every state DAgger can visit
            self.demos = JointReplay(min(most, 2**31 - 1), runs=self.runs, device=self.device)
        # explicit streams per run and purpose, on the device (``algos.streams``), never global state: replay draws,
        # exploration (and CoDBC's teacher share), noise (DIAL's DRU, Gumbel messages, a noisy channel control)
        self.streams = {name: RunStreams(self.seeds, name, self.device) for name in STREAMS}
        self.n_actions_np = np.asarray(spec.n_actions, dtype=np.int64)
        self.action_counts = torch.as_tensor(self.n_actions_np, device=self.device)  # [N]
        mask = torch.arange(self.n_act)[None, :] < torch.as_tensor(spec.n_actions)[:, None]
        self.action_mask = mask.to(self.device)  # [N, A]
        self.hold = Hold.zeta(cfg.eps_hold_mu, cfg.eps_hold_max, self.device) if cfg.eps_hold_max > 1 else None
        self.progress = Progress()
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
        self._members: dict[int, NetworkAgent] = {}
        self.run_cfgs: list[AlgoConfig] = [cfg] * len(self.seeds)
        self.gamma: float | Tensor = cfg.gamma
        self.alpha: float | Tensor = cfg.advantage_learning
        # the update: Adam, clip, guard, target sync, figures and their checkpoint state (``algos/updater.py``)
        nets = (self.online, self.target, self.average)
        self.updater = Updater(self.name, self.seeds, nets, self.streams, self.objective, self.run_cfgs,
                               self.syncs_by_updates)  # fmt: skip

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
        self.updater.set_run_configs(configs)  # refused once the runs have stepped
        self.run_cfgs, self.cfg = list(configs), configs[0]
        gammas, alphas = [c.gamma for c in configs], [c.advantage_learning for c in configs]
        self.gamma = gammas[0] if len(set(gammas)) == 1 else torch.tensor(gammas, device=self.device).reshape(-1, 1)
        self.alpha = alphas[0] if len(set(alphas)) == 1 else torch.tensor(alphas, device=self.device).reshape(-1, 1, 1)

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
    def observe(self, chunk: Transition[np.ndarray], valid: np.ndarray | None = None) -> None:
        """Chunks ``[T, R, B, …]`` (a single run's may leave out its run axis, ``[T, B, …]``) as rows in time-major
        order, per run; ``valid [T, R, B]`` keeps only those rows (each run's meta-transitions, in hierarchical
        DQN). With ``n_step`` > 1 the rows are multi-step transitions (``n_step_rows``)."""
        chunk = with_run_axis(chunk, self.runs)
        if self.cfg.n_step > 1:
            gamma = self.gamma.cpu().numpy().reshape(-1) if isinstance(self.gamma, Tensor) else self.gamma
            chunk = n_step_rows(chunk, self.cfg.n_step, gamma)
        runs = chunk.map(lambda v: v.swapaxes(0, 1).reshape(self.runs, -1, *v.shape[3:]))
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
        gathered on the device; with ``demo_margin``, as many of the run's demonstrations beside them."""
        if not self.replay.prioritized:
            batch = self.replay.sample(self.cfg.batch_size, self.streams["replay"])
        else:
            beta0: float = getattr(self.cfg, "priority_beta", 1.0)  # at the run's start; 1 by its end
            beta = beta0 + (1.0 - beta0) * run_fraction(self.progress.env_steps, self.progress.total_steps)
            batch, self._drawn, weight = self.replay.sample_prioritized(
                self.cfg.batch_size, self.streams["replay"], beta
            )
            batch.extras["is_weight"] = weight
        if self.demos is not None and len(self.demos):
            batch.extras.update(self.demos.sample_columns(self.cfg.batch_size, self.streams["replay"]))
        return batch

    def keep_demonstrations(self, obs: Sequence[np.ndarray], actions: Sequence[np.ndarray]) -> None:
        """Keep run k's DAgger states ``obs[k] [M_k, N, D]`` and the teacher's actions there ``actions[k] [M_k, N]``
        for ``demo_margin`` (runs may hold different counts)."""
        if self.demos is None:
            raise ValueError("keep_demonstrations: this agent's demo_margin is 0; it keeps no demonstrations")
        counts = np.array([len(o) for o in obs])
        m = int(counts.max())

        def padded(arrays: Sequence[np.ndarray], dtype: type) -> np.ndarray:
            return np.stack([np.concatenate([a, np.zeros((m - len(a), *a.shape[1:]), a.dtype)]) for a in arrays]
                            ).astype(dtype)  # fmt: skip

        self.demos.reserve(m)
        self.demos.add_columns({"demo_obs": padded(obs, np.float32), "demo_action": padded(actions, np.int64)},
                               valid=np.arange(m)[None, :] < counts[:, None])  # fmt: skip

    def objective(self, batch: Batch) -> Loss:
        """What an update minimises: the algorithm's ``loss``, plus ``demo_margin`` × DQfD's large-margin loss on the
        batch's demonstrations where the run keeps them (Hester et al. 2018, eq. 2 and 5)."""
        out = self.loss(batch)
        if "demo_action" not in batch.extras:
            return out
        q = self.imitation_logits(batch.extras["demo_obs"])  # through the channel, as the clone was trained
        margin = large_margin(q, batch.extras["demo_action"], self.action_mask)
        return out.plus(self.demo_margin * margin, {"demo_margin": margin.detach()})

    def imitation_logits(self, obs: Tensor) -> Tensor:
        """Q-values ``[R, b, N, A]`` read as a clone's logits (``learner/imitation.py``): the learners a demonstrator
        can start define it."""
        raise NotImplementedError(f"{self.name} cannot start from a demonstrator")

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

    def env_epsilon(self, epsilon: float | np.ndarray, envs: int) -> np.ndarray:
        """ε per run and env ``[R, B]`` from a scalar, one per run ``[R]`` or one per run and env."""
        eps = np.asarray(epsilon, dtype=np.float64)
        return np.broadcast_to(eps.reshape(self.runs, -1) if eps.ndim else eps, (self.runs, envs))

    def explore(self, q: Tensor, epsilon: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``epsilon_greedy`` for this agent on Q ``[R, B, N, A]``, one greedy pass and one draw for every run (ε a
        scalar, one per run ``[R]`` or per run and env ``[R, B]``; a single run's may be one per env ``[B]``): the
        actions, the greedy actions and ε per env and agent, ``[R, B, N]``."""
        eps = self.env_epsilon(epsilon, q.shape[1])
        actions, greedy = epsilon_greedy(q, eps, self.action_mask, self.action_counts, self.streams["explore"],
                                         self.hold)  # fmt: skip
        return actions, greedy, np.broadcast_to(eps[..., None], actions.shape)

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

    @property
    def updates(self) -> int:
        """``update()`` calls so far (the updater's count: a skipped one too)."""
        return self.updater.updates

    # --- learning: the algorithm's loss, the updater's step ------------------------------------------------------
    def agent_losses(self, batch: Batch) -> Tensor:
        """Each run's agents' losses ``[R, N]`` on ``batch`` (tests back-propagate one to see which weights it
        reaches)."""
        return self.loss(batch).agents

    def update(self) -> Figures:
        """One guarded gradient step of ``loss`` on a sampled batch, and the target sync (``Updater.update``)."""
        batch = self.sample()
        figures = self.updater.update(batch, run_fraction(self.progress.env_steps, self.progress.total_steps))
        if self._drawn is not None and self.updater.priority is not None:
            self.replay.set_priorities(self._drawn, (self.updater.priority + PRIORITY_FLOOR) ** self.priority_alpha)
        return figures

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
        """Run k's state as a single run's ``state_dict``: the updater's (networks, targets, Adam, update count,
        random streams; no run axis) and what the algorithm adds (``member_state``)."""
        return {**self.updater.run_state_dict(k), **self.member_state(k)}

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
        agent.updater.skipped_updates = self.updater.skipped_updates
        return agent

    def member_state(self, k: int) -> dict[str, Any]:
        """What an algorithm adds to run k's ``state_dict`` beyond the networks, optimizer and streams."""
        return {}

    def load_member_state(self, k: int, state: dict[str, Any]) -> None:
        """Put a single run's state (``member(k).state_dict()``, a checkpoint's: no run axis) into run k: how a
        run resumes from its checkpoint, and a population from its runs'."""
        self.updater.load_run_state(k, state)
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
