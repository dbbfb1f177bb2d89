"""Hierarchical DQN (Kulkarni et al. 2016; the paper's appendix A.2) on the treadmill: a meta-controller picks
sub-goals, a goal-conditioned controller reaches them with the 9 primitive actions.

Goals. Five driving manoeuvres that can be read off an agent's own observation (lateral position, heading one-hot,
speed; see ``docs/treadmill.md``):

======  ================================  ===============================================================
goal    asks for                          reached when, compared with the anchor (the option's first obs)
======  ================================  ===============================================================
cruise  keep the lane at treadmill speed  heading forward (h = 0) and speed = treadmill speed
left    move one lane (cell) towards +y   lateral position grew by ≥ 1 cell
right   move one lane (cell) towards −y   lateral position shrank by ≥ 1 cell
faster  raise the speed one level         speed ≥ anchor speed + 1
slower  lower the speed one level         speed ≤ anchor speed − 1
======  ================================  ===============================================================

Internal critic (``GoalCritic``). Compares each agent's anchor observation with its current one (after one step of
an option these are consecutive observations). A goal is never "reached" by crashing: on a step that terminates the
episode the critic's verdict is overruled.

Options. The agents of one env run their options in lockstep, so the meta level takes one joint step per env: it
picks a goal per agent when the env's option starts, and the option ends as soon as *some* agent reaches its goal,
after ``goal_steps`` steps, or when the episode ends — the meta-controller then re-plans every agent (it may well
give an unfinished agent the same goal again). Waiting for *every* agent instead makes early finishers idle in some
holding pattern that undoes their goal (a car that sped up and then cruises slows down again); on the small
treadmill (2 agents, one seed) that variant reached a greedy return of 3 against 27 after 80k steps.

Meta-controller. The job's algorithm (any of idqn, dqn-ser, ma-mesn, ma-bon, ims, dial), built for a spec like the
env's but with ``n_goals`` actions per agent and ``ceil(max_steps / goal_steps)`` steps, acting (ε-greedy, with its
own recurrent state and messages) only for the envs that start an option. It learns from meta-transitions: the
option's first observation, the goals, the env reward summed over the option, ``R = Σ_k γ^k r_{t+k}`` per agent,
the observation the option ended on, the env's terminated/truncated flags and ``discount = γ^τ`` for an option of
τ steps, which the shared TD target (``algos.algorithm.td_target``) bootstraps with: with one γ per meta step,
options that last longer collect more reward per meta step and the meta-controller learned to prefer goals that
never finish. Meta-transitions of
the envs whose option ended in a step go to ``meta.observe`` as one ``[1, M]`` chunk.

DIAL at the meta level. DIAL learns from ``[T, B]`` sequences (``chunk_len = unroll``) that unroll its messages
through time, which needs the same envs in every row and a fixed time unit. So with DIAL options have a fixed
length: they end only after ``goal_steps`` steps or at the episode's end, and an agent that reaches its goal earlier
ends its intrinsic episode and pursues the same goal again from a new anchor (another lane, another speed level).
Each env's meta-transitions queue up (``LockstepQueue``) and a ``[T, B]`` chunk is released once every env holds T
of them; an env that runs ahead (its episodes ended more often) drops its oldest queued ones, so each column stays a
contiguous run of that env's meta steps, which DIAL restarts from their stored ``msg_in``. DIAL bootstraps with its
own γ per meta step (τ is constant except at episode ends, where the episode's flags decide).

Controller. An independent double DQN (``IndependentDQN``) whose input is ``obs ⊕ one_hot(goal)``. Its spec has a
single agent and every (env, agent) pair is one row, so all agents share its weights and each agent's intrinsic
episode ends on its own; replay capacity, batch and warm-up are scaled by N so an update sees as many agent
transitions as one of a joint algorithm. Its reward has A.2's form
``Q*(z_c, a; g) = E[r*(z_c, a; g) + γ r(z, a) + E Q^T(z_c', a'; g)]``: the critic's intrinsic reward r* (+1 when the
goal is reached) plus the env reward r scaled by ``env_reward_scale``, bootstrapped with γ as usual. The scale
defaults to 1 − γ rather than the formula's γ: reaching the goal ends the intrinsic episode, and with the env reward
at full weight that terminal forfeits ≈ r̄ / (1 − γ) ≈ 50 of future env reward against +1 for reaching, so the
controller learned to avoid its goals (0 % reached for left/right/faster); at 1 − γ the env reward it could collect
forever is ≤ 1, so it shapes how a goal is reached (and punishes crashes) without outweighing reaching it. A step is
terminal for the controller when its goal was reached or the episode terminated; an option that times out
bootstraps.

Acting vs learning. ``act`` decides option boundaries from observations alone, so greedy evaluation (which never
calls ``observe``) acts exactly as in training; it stamps the goals, the option-start flag and the step count into
``extras``. The meta-controller acts for every env at every step and its goal counts where an option starts: so its
exploration stream advances alike whichever envs start options, which a population needs (below). ``observe``
(every step, ``chunk_len = 1``) reruns the same critic on the stored transition, writes controller rows and keeps
the per-env reward sums that become meta-transitions. ε applies to both levels; each ``update`` takes one gradient
step on each level that can learn. The meta level learns once its replay is warm, judged by a clock every run
shares: ``goal_steps · (max(learning_starts, batch_size) + B)`` env steps observed (B envs per run), after which
each run holds at least ``max(learning_starts, batch_size)`` meta-transitions (an option lasts ≤ ``goal_steps``).

Populations. Given a job with ``seeds``, both levels are populations of R runs (``[R, B, …]`` observations,
``[T, R, B, …]`` chunks) and run k is the single run of seed k: its meta-transitions go to run k's own ring
(``JointReplay.add(rows, valid)``: runs end options at different steps), and the meta's warm-up clock above is the
same for all runs, where "each run's replay holds enough rows" would start the runs' meta updates at different
update counts. A DIAL meta-controller (fixed options released in lockstep chunks) trains one seed per process.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from operator import itemgetter
from typing import Any

import numpy as np
import torch
from torch import Tensor

from convoy.algos.algorithm import ActOutput, NetworkAgent, Progress, with_run_axis
from convoy.algos.idqn import IndependentDQN
from convoy.algos.nets import pick_device
from convoy.algos.registry import make_algorithm
from convoy.algos.updater import Figures
from convoy.config import AlgoConfig, IDQNConfig, JobConfig
from convoy.envs.batched import EnvSpec
from convoy.envs.treadmill.config import N_HEADINGS, TreadmillConfig
from convoy.transition import Transition, from_columns

GOALS: tuple[str, ...] = ("cruise", "left", "right", "faster", "slower")
CRUISE, LEFT, RIGHT, FASTER, SLOWER = range(len(GOALS))
N_GOALS = len(GOALS)
LATERAL, HEADING, SPEED = 0, slice(1, 1 + N_HEADINGS), 1 + N_HEADINGS  # own features of a treadmill observation
META_PREFIX = "meta/"  # extras of the meta-controller's act, carried to its transitions


# independent DQN settings the controller takes from a job that has them (``_controller_config``)
CONTROLLER_TAKES = ("dueling", "priority_alpha", "priority_beta")


class GoalCritic:
    """Internal critic: has each agent reached its goal between two observations of the same episode?"""

    def __init__(self, cfg: TreadmillConfig) -> None:
        self.half_width = (cfg.width - 1) / 2.0  # obs[LATERAL] = 2y/(width−1) − 1
        self.max_speed = cfg.max_speed
        self.treadmill_speed = cfg.treadmill_speed

    def lateral(self, obs: np.ndarray) -> np.ndarray:
        """Lateral position in cells (0 = the right edge)."""
        return (obs[..., LATERAL] + 1.0) * self.half_width

    def speed(self, obs: np.ndarray) -> np.ndarray:
        speed: np.ndarray = np.rint(obs[..., SPEED] * self.max_speed).astype(np.int64)  # numpy leaves obs[...] untyped
        return speed

    def heading(self, obs: np.ndarray) -> np.ndarray:
        heading: np.ndarray = np.argmax(obs[..., HEADING], axis=-1)
        return heading

    def reached(self, goal: np.ndarray, anchor: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """``[..., N]`` bool: goal ``[..., N]`` met by ``obs [..., N, D]`` relative to ``anchor [..., N, D]``."""
        dy = self.lateral(obs) - self.lateral(anchor)
        v0, v = self.speed(anchor), self.speed(obs)
        met = np.stack(
            [
                (self.heading(obs) == 0) & (v == self.treadmill_speed),  # cruise
                dy >= 0.5,  # left: ≥ one cell (positions are whole cells; 0.5 absorbs float error)
                dy <= -0.5,  # right
                v >= v0 + 1,  # faster
                v <= v0 - 1,  # slower
            ],
            axis=-1,
        )
        return np.take_along_axis(met, goal[..., None].astype(np.int64), axis=-1)[..., 0]


@dataclass
class HierState:
    """Acting state per env: the option in progress and the meta-controller's own recurrent state."""

    goal: np.ndarray  # [B, N] int64, goals the meta-controller gave for the current option
    anchor: np.ndarray  # [B, N, D] observation each agent's goal is judged against (the option's first, or later)
    steps: np.ndarray  # [B] int64, steps taken in the option
    fresh: np.ndarray  # [B] bool, a new option must start (first step, or the episode just ended)
    meta: Any = None  # the meta-controller's recurrent state (DIAL's last messages), rows = envs
    messages: np.ndarray | None = None  # [B, N, …] the meta's messages at each env's last meta step


def _take(state: Any, idx: np.ndarray) -> Any:
    """Rows ``idx`` (envs: indices, or a boolean mask over the leading env dims) of a recurrent state made of
    tensors / arrays / containers of them."""
    if state is None:
        return None
    if isinstance(state, Tensor):
        return state[torch.as_tensor(idx, device=state.device)]
    if isinstance(state, np.ndarray):
        return state[idx]
    if isinstance(state, (tuple, list)):
        return type(state)(_take(s, idx) for s in state)
    if isinstance(state, dict):
        return {k: _take(v, idx) for k, v in state.items()}
    raise TypeError(f"hierarchy: cannot slice a meta-controller state of type {type(state).__name__}")


def _put(state: Any, idx: np.ndarray, rows: Any) -> Any:
    """A copy of ``state`` with rows ``idx`` (as in ``_take``) replaced by ``rows`` (same structure)."""
    if state is None or rows is None:
        return state
    if isinstance(state, Tensor):
        out = state.clone()
        out[torch.as_tensor(idx, device=state.device)] = rows.to(out.dtype)
        return out
    if isinstance(state, np.ndarray):
        arr = state.copy()
        arr[idx] = rows
        return arr
    if isinstance(state, (tuple, list)):
        return type(state)(_put(s, idx, r) for s, r in zip(state, rows, strict=True))
    if isinstance(state, dict):
        return {k: _put(v, idx, rows[k]) for k, v in state.items()}
    raise TypeError(f"hierarchy: cannot update a meta-controller state of type {type(state).__name__}")


class LockstepQueue:
    """Per-env FIFOs of meta-transitions, released as ``[T, B]`` chunks once every env holds T (DIAL's layout).

    An env that runs ahead drops its oldest entries beyond ``capacity``, so what it releases stays contiguous.
    """

    def __init__(self, length: int, capacity: int) -> None:
        self.length, self.capacity = length, max(capacity, length)
        self.buf: dict[str, np.ndarray] = {}
        self.count = np.zeros(0, dtype=np.int64)

    def push(self, num_envs: int, envs: np.ndarray, rows: dict[str, np.ndarray]) -> None:
        """Append one meta-transition for each of ``envs`` (distinct) in a batch of ``num_envs``."""
        if not self.buf or len(self.count) != num_envs or set(rows) != set(self.buf):
            self.buf = {k: np.zeros((num_envs, self.capacity, *v.shape[1:]), v.dtype) for k, v in rows.items()}
            self.count = np.zeros(num_envs, dtype=np.int64)
        full = envs[self.count[envs] >= self.capacity]
        if full.size:
            for v in self.buf.values():
                v[full, :-1] = v[full, 1:].copy()
            self.count[full] -= 1
        slot = self.count[envs]
        for k, v in self.buf.items():
            v[envs, slot] = rows[k]
        self.count[envs] += 1

    def pop(self) -> dict[str, np.ndarray] | None:
        """The oldest T meta-transitions of every env as ``[T, B, …]``, or None while some env has fewer."""
        t = self.length
        if not self.buf or self.count.min() < t:
            return None
        out = {k: np.ascontiguousarray(v[:, :t].swapaxes(0, 1)) for k, v in self.buf.items()}
        for v in self.buf.values():
            v[:, : self.capacity - t] = v[:, t:].copy()
        self.count -= t
        return out


@dataclass(frozen=True)
class LevelFigures(Figures):
    """Both levels' figures of one update: ``controller_loss`` and ``meta_loss`` (NaN for a level that did not
    learn) and ``loss``, their sum; read as each level's are, in the same host read."""

    n_runs: int
    levels: dict[str, Figures]  # the levels that learned in this update

    def tensors(self) -> list[Tensor]:
        return [t for figures in self.levels.values() for t in figures.tensors()]

    def rows(self, host: list[np.ndarray]) -> list[dict[str, float]]:
        rows = [{"loss": 0.0, "controller_loss": math.nan, "meta_loss": math.nan} for _ in range(self.n_runs)]
        for level, figures in self.levels.items():
            n = len(figures.tensors())
            own, host = host[:n], host[n:]
            for row, values in zip(rows, figures.rows(own), strict=True):
                row[f"{level}_loss"] = values["loss"]
                row["loss"] += values["loss"]
        return rows


class HierarchicalAgent:
    """Meta-controller (the job's algorithm over goals) + goal-conditioned double-DQN controller, driven through the
    calls of the ``Agent`` protocol (act / observe / can_update / updates_for / update / state_dict)."""

    chunk_len: int = 1

    def __init__(
        self,
        job: JobConfig,
        spec: EnvSpec,
        device: str | torch.device = "auto",
        goal_steps: int = 4,
        env_reward_scale: float | None = None,
    ) -> None:
        if job.env != "treadmill":
            raise ValueError(f"hierarchy: goals are defined for the treadmill only (env is {job.env!r})")
        if goal_steps < 1:
            raise ValueError(f"goal_steps: must be ≥ 1 (got {goal_steps})")
        if len(set(spec.n_actions)) != 1:
            raise ValueError(f"hierarchy: the controller needs one action count for all agents, got {spec.n_actions}")
        env_cfg = job.env_config()
        if not isinstance(env_cfg, TreadmillConfig):
            raise TypeError(f"hierarchy: needs a TreadmillConfig, got {type(env_cfg).__name__}")
        self.job, self.spec = job, spec
        self.cfg: AlgoConfig = job.algo_config()
        self.device = pick_device(device) if isinstance(device, str) else device
        self.n_agents, self.obs_dim = spec.n_agents, spec.obs_dim
        self.goal_steps = int(goal_steps)
        self.critic = GoalCritic(env_cfg)
        self.goal_eye = np.eye(N_GOALS, dtype=np.float32)

        meta_spec = EnvSpec(
            name=f"{spec.name}-meta",
            agent_ids=spec.agent_ids,
            obs_dims=spec.obs_dims,
            n_actions=(N_GOALS,) * spec.n_agents,
            max_steps=math.ceil(spec.max_steps / self.goal_steps),
            layout=spec.layout,  # the meta level reads the env's observations
        )
        self.seeds: tuple[int, ...] = tuple(job.run_seeds())
        self.runs = len(self.seeds)  # a single run is a population of one
        self.meta: NetworkAgent = make_algorithm(job.algo, meta_spec, self.cfg, device=self.device, seed=self.seeds)
        ctrl_spec = EnvSpec(
            name=f"{spec.name}-controller",
            agent_ids=("controller",),
            obs_dims=(spec.obs_dim + N_GOALS,),
            n_actions=(spec.max_actions,),
            max_steps=spec.max_steps,
        )
        self.controller: NetworkAgent = IndependentDQN(
            ctrl_spec,
            self._controller_config(self.cfg),
            device=self.device,
            seed=[s + 1 for s in self.seeds],
        )
        self.env_reward_scale = float(1.0 - self.cfg.gamma if env_reward_scale is None else env_reward_scale)
        self.name = f"h-{self.meta.name}"
        self.uses_messages = self.meta.uses_messages
        self.updates = 0
        self.meta_steps = 0  # env steps observed per run: the meta level's warm-up clock
        self._envs = 0  # envs per run, seen in the chunks
        self.run_cfgs: list[AlgoConfig] = [self.cfg] * len(self.seeds)
        self._members: dict[int, HierarchicalAgent] = {}
        self._progress = Progress()
        self._pending: dict[str, Any] = {}
        # DIAL learns from [T, B] sequences: options of fixed length there (see the module docstring); every other
        # meta algorithm gets variable-length options and an SMDP target
        self.fixed_options = self.meta.chunk_len > 1
        self._queue = LockstepQueue(self.meta.chunk_len, 2 * self.meta.chunk_len) if self.fixed_options else None
        if self.fixed_options and self.runs > 1:
            raise ValueError("hierarchy: a DIAL meta-controller trains one seed per process (drop seeds)")

    def _controller_config(self, cfg: AlgoConfig) -> IDQNConfig:
        """The controller's config from the job's: shared weights over every (env, agent) row, and replay capacity,
        batch and warm-up scaled by N so an update sees as many agent transitions as one of a joint algorithm. Of
        independent DQN's own settings it takes those that leave its input and acting alone (``CONTROLLER_TAKES``:
        the dueling head, prioritized replay); the encoder and Bootstrapped heads stay the MLP and one head, as its
        input ``obs ⊕ one_hot(goal)`` has no car layout and it acts row by row without an episode's head."""
        n = self.n_agents
        base = {k: getattr(cfg, k) for k in (*AlgoConfig.model_fields, *CONTROLLER_TAKES) if hasattr(cfg, k)}
        base.update(
            share_params=True,
            batch_size=cfg.batch_size * n,
            replay_capacity=cfg.replay_capacity * n,
            learning_starts=cfg.learning_starts * n,
        )
        return IDQNConfig(**base)

    def set_run_configs(self, configs: list[AlgoConfig]) -> None:
        """Each run's own hyper-parameters (a population; as ``NetworkAgent.set_run_configs``), γ excepted: it sets
        the controller's reward scale and the options' discount, one for the whole population here."""
        if len({c.gamma for c in configs}) > 1:
            raise ValueError("gamma: the runs of a hierarchical population share it; sweep it in separate jobs")
        self.meta.set_run_configs(configs)
        self.controller.set_run_configs([self._controller_config(c) for c in configs])
        self.run_cfgs, self.cfg = list(configs), configs[0]

    # --- shared counters ---------------------------------------------------------------------------------------
    @property
    def progress(self) -> Progress:
        return self._progress

    @progress.setter
    def progress(self, value: Progress) -> None:
        """Both levels follow the trainer's clock (ε schedules, SER ages, DIAL's importance weights)."""
        self._progress = value
        self.meta.progress = value
        self.controller.progress = value

    def n_parameters(self) -> int:
        return self.meta.n_parameters() + self.controller.n_parameters()

    def reserve_replay(self, env_steps: int) -> None:
        """Replay for at most ``env_steps`` joint env steps: the controller stores N rows per step (one per agent),
        the meta level at most one per step (an option lasts ≥ 1 step)."""
        self.controller.reserve_replay(env_steps * self.n_agents)
        self.meta.reserve_replay(env_steps)

    # --- acting ------------------------------------------------------------------------------------------------
    def initial_state(self, num_envs: int) -> HierState:
        """Every env starts a new option at its first step (``num_envs`` per run, ``[R, B, …]``)."""
        lead = (self.runs, num_envs)
        return HierState(
            goal=np.zeros((*lead, self.n_agents), dtype=np.int64),
            anchor=np.zeros((*lead, self.n_agents, self.obs_dim), dtype=np.float32),
            steps=np.zeros(lead, dtype=np.int64),
            fresh=np.ones(lead, dtype=bool),
            meta=self.meta.initial_state(num_envs),
        )

    def reset_state(self, state: HierState | None, done: np.ndarray) -> HierState | None:
        """An episode's end ends its option: the env starts a new one (and a fresh meta state) at its next act."""
        if state is None:
            return None
        done = np.asarray(done, dtype=bool).reshape(self.runs, -1)
        return replace(state, fresh=state.fresh | done, meta=self.meta.reset_state(state.meta, done))

    def controller_input(self, obs: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """``obs ⊕ one_hot(goal)`` as controller rows ``[R, B·N, 1, D + n_goals]``."""
        x = np.concatenate([obs.astype(np.float32, copy=False), self.goal_eye[goal]], axis=-1)
        return x.reshape(*obs.shape[:-3], -1, 1, x.shape[-1])

    def option_over(self, steps: np.ndarray, hit: np.ndarray) -> np.ndarray:
        """``[B]``: the env's option ends (before its episode does): ``goal_steps`` taken, or (variable options) some
        agent reached its goal."""
        over = steps >= self.goal_steps
        return over if self.fixed_options else over | hit.any(axis=-1)

    def act(self, obs: np.ndarray, epsilon: float | np.ndarray = 0.0, state: HierState | None = None) -> ActOutput:
        """``NetworkAgent.act``: ``obs [R, B, N, D]``, or a single run's ``[B, N, D]`` (what comes back then has no
        run axis either)."""
        eps = np.asarray(epsilon, dtype=np.float64)
        runs = np.reshape(obs, (self.runs, -1, *np.shape(obs)[-2:]))
        return self.act_runs(runs, eps.reshape(self.runs, -1) if eps.ndim else eps, state).shaped(obs.shape[:-2])

    @torch.no_grad()
    def act_runs(self, obs: np.ndarray, epsilon: float | np.ndarray, state: HierState | None) -> ActOutput:
        """New goals for envs whose option is over (meta, ε-greedy), then primitive actions (controller, ε-greedy),
        ``obs [R, B, N, D]``, ε a scalar or ``[R, 1 or B]``.

        Option boundaries are judged here from the observations alone, so acting without ``observe`` (evaluation)
        is the same as in training.
        """
        lead, n = obs.shape[:-2], self.n_agents
        st = self.initial_state(lead[-1]) if state is None else state
        eps = np.broadcast_to(epsilon, lead)
        hit = self.critic.reached(st.goal, st.anchor, obs) & ~st.fresh[..., None]
        new = st.fresh | self.option_over(st.steps, hit)
        steps = np.where(new, 0, st.steps) + 1
        anchor = np.where((hit | new[..., None])[..., None], obs, st.anchor).astype(np.float32)
        mo = self.meta.act(obs, eps, st.meta)  # every env, every step: see the module docstring
        goal = np.where(new[..., None], mo.actions, st.goal)
        meta_state = _put(st.meta, new, _take(mo.state, new))
        messages = st.messages
        if mo.messages is not None:
            fits = messages is not None and messages.shape == mo.messages.shape
            messages = messages.copy() if messages is not None and fits else np.zeros_like(mo.messages)
            messages[new] = mo.messages[new]
        extras = {META_PREFIX + k: v for k, v in mo.extras.items()}  # read where an option starts
        co = self.controller.act(self.controller_input(obs, goal), np.repeat(eps, n, axis=-1), None)
        extras.update(h_goal=goal, h_start=new, h_steps=steps)
        return ActOutput(
            actions=co.actions.reshape(*lead, n),
            messages=None if messages is None else messages.copy(),
            extras=extras,
            state=HierState(goal, anchor, steps, np.zeros(lead, dtype=bool), meta_state, messages),
        )

    # --- learning ----------------------------------------------------------------------------------------------
    def observe(self, chunk: Transition[np.ndarray]) -> None:
        """Controller rows for every step of a ``[T, R, B]`` chunk (a single run's may be ``[T, B]``),
        meta-transitions for the options that ended."""
        chunk = with_run_axis(chunk, self.runs)
        for t in range(chunk.obs.shape[0]):
            self._observe_step(chunk.map(itemgetter(t)))
            self._envs = chunk.obs.shape[-3]
            self.meta_steps += self._envs

    def _open_options(self, s: Transition[np.ndarray]) -> dict[str, Any]:
        """The learner's per-env option bookkeeping (first obs, critic anchors, reward sums, the meta's extras),
        reset where ``act`` started an option. An option still open there was cut short unseen and is dropped."""
        lead = s.obs.shape[:-2]
        p = self._pending
        if not p or p["open"].shape != lead:
            p.clear()
            p.update(
                open=np.zeros(lead, dtype=bool),
                first=np.zeros_like(s.obs, dtype=np.float32),
                anchor=np.zeros_like(s.obs, dtype=np.float32),
                ret=np.zeros((*lead, self.n_agents), dtype=np.float32),
                disc=np.ones(lead, dtype=np.float32),
                extras={k: np.zeros_like(v) for k, v in s.extras.items() if k.startswith(META_PREFIX)},
            )
        new = s.extras["h_start"].astype(bool)
        if new.any():
            p["open"][new] = True
            p["first"][new] = s.obs[new]
            p["anchor"][new] = s.obs[new]
            p["ret"][new] = 0.0
            p["disc"][new] = 1.0
            for k, v in p["extras"].items():
                v[new] = s.extras[k][new]
        return p

    def _observe_step(self, s: Transition[np.ndarray]) -> None:
        """One step ``[R, B, …]``: every agent's controller transition, then the meta-transitions of ended options."""
        p = self._open_options(s)
        obs, nxt = s.obs, s.next_obs
        term, trunc = s.terminated.astype(bool), s.truncated.astype(bool)
        goal, reward = s.extras["h_goal"].astype(np.int64), s.reward.astype(np.float32)
        lead, n = goal.shape[:-1], goal.shape[-1]
        rows = (*lead[:-1], -1)  # the controller's: one per (env, agent), per run
        hit = self.critic.reached(goal, p["anchor"], nxt) & ~term[..., None]

        ctrl = Transition(
            obs=self.controller_input(obs, goal),
            action=s.action.reshape(*rows, 1),
            reward=(hit + self.env_reward_scale * reward).reshape(*rows, 1).astype(np.float32),
            next_obs=self.controller_input(nxt, goal),
            terminated=(hit | term[..., None]).reshape(rows),
            truncated=np.repeat(trunc, n, axis=-1),
            episode=np.repeat(s.episode, n, axis=-1),
        )
        self.controller.observe(ctrl.map(lambda v: v[None]))
        p["anchor"] = np.where(hit[..., None], nxt, p["anchor"])  # fixed options: the goal is pursued again

        p["ret"] += p["disc"][..., None] * reward
        p["disc"] *= float(self.meta.cfg.gamma)
        ended = p["open"] & (self.option_over(s.extras["h_steps"], hit) | term | trunc)
        if not ended.any():
            return
        meta_rows = Transition(  # [R, B, …]: every env's, ``ended`` the ones that are meta-transitions
            obs=p["first"],
            action=goal,
            reward=p["ret"],
            next_obs=nxt,
            terminated=term,
            truncated=trunc,
            episode=s.episode,
            extras={
                **({} if self.fixed_options else {"discount": p["disc"]}),
                **{k[len(META_PREFIX) :]: v for k, v in p["extras"].items()},
            },
        )
        p["open"][ended] = False
        if self._queue is None:
            self.meta.observe(meta_rows.map(lambda v: v[None]), valid=ended[None])
            return
        envs = np.flatnonzero(ended[0])  # DIAL's lockstep sequences: fixed options, one run
        self._feed_meta(lead[-1], envs, meta_rows.map(lambda v: v[0, envs]))

    def _feed_meta(self, num_envs: int, envs: np.ndarray, rows: Transition[np.ndarray]) -> None:
        """Hand DIAL's meta-transitions to the meta-controller as ``[T, B]`` lockstep chunks."""
        assert self._queue is not None
        self._queue.push(num_envs, envs, rows.columns())
        while (chunk := self._queue.pop()) is not None:
            self.meta.observe(from_columns(chunk))

    def meta_can_update(self) -> bool:
        """The meta level learns once the clock every run shares says its replay is warm (module docstring); DIAL
        by its own rule over its sequences."""
        if self.fixed_options:
            return self.meta.can_update()
        cfg = self.meta.cfg
        warm = self.goal_steps * (max(cfg.learning_starts, cfg.batch_size) + self._envs)
        return self.meta_steps >= warm and len(self.meta.replay) > 0

    def can_update(self) -> bool:
        return self.controller.can_update() or self.meta_can_update()

    def updates_for(self, n_transitions: int) -> float:
        """Updates owed for ``n_transitions`` joint env steps: the controller's replay ratio over its N rows each."""
        return self.controller.updates_for(n_transitions * self.n_agents)

    def update(self) -> LevelFigures:
        """One controller step and one meta step, each when its level can learn (a population's figures per run,
        left on the device as each level's are).

        An option spans ≥ 1 steps, so the meta level receives at most as many meta-transitions as there are joint
        env steps; one meta step per call gives it at least the controller's replay ratio on its own (scarcer) data.
        """
        learns = {"controller": self.controller.can_update(), "meta": self.meta_can_update()}  # asked before either
        levels: dict[str, Figures] = {}
        for level, algo in (("controller", self.controller), ("meta", self.meta)):
            if learns[level]:
                levels[level] = algo.update()
        self.updates += 1
        return LevelFigures(len(self.seeds), levels)

    # --- persistence -------------------------------------------------------------------------------------------
    def policy_state(self) -> dict[str, Tensor]:
        """Both levels' online weights (CPU), keys prefixed ``meta.`` / ``controller.``."""
        out = {f"meta.{k}": v for k, v in self.meta.policy_state().items()}
        out.update({f"controller.{k}": v for k, v in self.controller.policy_state().items()})
        return out

    def load_policy_state(self, state: dict[str, Tensor]) -> None:
        for prefix, algo in (("meta.", self.meta), ("controller.", self.controller)):
            algo.load_policy_state({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})

    def state_dict(self) -> dict[str, Any]:
        """Both levels' full state plus the wrapper's counters and option settings."""
        return {
            "meta": self.meta.state_dict(),
            "controller": self.controller.state_dict(),
            "updates": self.updates,
            "meta_steps": self.meta_steps,
            "goal_steps": self.goal_steps,
            "env_reward_scale": self.env_reward_scale,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.goal_steps = int(state["goal_steps"])  # an option setting, not a network shape: the file wins
        self.meta.load_state_dict(state["meta"])
        self.controller.load_state_dict(state["controller"])
        self._load_counters(state)
        self.env_reward_scale = float(state["env_reward_scale"])

    def _load_counters(self, state: dict[str, Any]) -> None:
        self.updates = int(state["updates"])
        # a checkpoint written before the warm-up clock existed: its meta level was learning already
        self.meta_steps = int(state.get("meta_steps", 1 << 62))

    # --- a population's runs as single runs ----------------------------------------------------------------------
    def member(self, k: int) -> HierarchicalAgent:
        """Run k of a population as a single-run hierarchical agent of its seed, both levels holding the run's
        current state (``NetworkAgent.member``): what its evaluation and checkpoints use. A run of one is its own."""
        if self.runs == 1:
            return self
        agent = self._members.get(k)
        if agent is None:
            agent = HierarchicalAgent(self.job.members()[k], self.spec, self.device, self.goal_steps,
                                      self.env_reward_scale)  # fmt: skip
            agent.cfg = self.run_cfgs[k]
            self._members[k] = agent
        agent.meta, agent.controller = self.meta.member(k), self.controller.member(k)
        agent.updates, agent.meta_steps, agent._envs = self.updates, self.meta_steps, self._envs
        agent._progress = agent.meta.progress
        return agent

    def load_member_state(self, k: int, state: dict[str, Any]) -> None:
        """A single run's state (a checkpoint's) into run k of a population: how a population resumes."""
        self.meta.load_member_state(k, state["meta"])
        self.controller.load_member_state(k, state["controller"])
        self._load_counters(state)
