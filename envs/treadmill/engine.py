"""The one treadmill physics: B highways × C cars stepped together with numpy.

Geometry. The treadmill is a ``length × width`` window of cells moving with the traffic: x runs along the road
(0 = the back, length−1 = the front), y across it (0 … width−1). Each car has a cell (x, y), a heading h ∈ 0…7
(h = 0 drives forward along +x, each step of h turns 45° to the left, towards +y) and a speed v ∈ 0…max_speed
cells per step. The treadmill carries every car ``treadmill_speed`` cells back per step, so a car driving forward
at that speed holds its place on the window; a faster car moves up, a slower one falls back.

Entering and leaving. Cars enter and exit at the front and back (the paper's "infinite highway"). An agent that
leaves the window — out the front, out the back or off a side — has left the road: it crashes. An adversary that
leaves at the front or back re-enters at once at a random lateral position, from the back at top speed or from
the front at speed 0 (so it falls back into the traffic); at a side it bounces (y clamped, heading mirrored).

Actions. 9 per car: (steer −45°, 0, +45°) × (decelerate, keep, accelerate), index ``3 * steer_index +
accel_index``. Cars 0…N−1 are the agents; N…N+M−1 are adversaries that each step, with probability
``aggression``, take the action whose one-step outcome lands closest to the nearest agent, else a uniformly
random action. An adversary driving faster than ``adversary_steer_speed`` (when set) cannot steer: its steering
actions keep its heading, so a fast chaser charges in a line and must slow down to turn.

Motion and collisions. A step is split into ``top_speed`` micro-steps (the fastest car's top speed:
``max_speed``, or ``adversary_speed`` if that is higher); a car with speed v moves one cell along its
heading in each of the first v micro-steps. After every micro-step two cars collide if they share a cell, or if
their moves crossed (a swap, or two diagonals through the same point: equal move midpoints). A crashed car stops
where it is. Collisions between two adversaries are ignored.

Rewards and episodes. Per agent and step, ``min(d, d_max) / d_max`` ∈ [0, 1] where d is the Euclidean distance in
cells to the closest other car (seen or not); a crashed agent gets ``−crash_penalty`` instead. Any agent crash
terminates the episode for all (cooperation: one car's mistake costs everyone); otherwise it is truncated after
``max_steps``. Finished envs reset themselves (see ``envs.batched``).

Observation per agent (features clipped to [−1, 1]): own lateral position, heading one-hot, speed / max_speed,
distance to each side edge / (width−1), longitudinal position on the window; then for each of the ``observe_k``
closest cars within ``sensor_range`` (agents and adversaries alike, as in the paper): a seen flag, relative
position / sensor_range, heading one-hot and speed / top_speed; a slot with no car in range is all zeros. With
``full_information`` (a reference, not the task) every other car follows: relative position / road size, speed
and an adversary flag. Agents spawn forward-facing at ``initial_speed`` on random distinct cells of a lattice of
pitch ``spawn_gap`` in the middle half of the window; adversaries enter at the front or back.

Randomness comes from ``envs.rng``: draws depend only on the env's own seed and step counter, so a batch equals
its envs stepped one by one, bit for bit (seed env b alone with ``envs.batched.env_seeds(s, B)[b]`` to replay env
b of a batch seeded s).
"""

from __future__ import annotations

import functools

import numpy as np

from convoy.envs import rng
from convoy.envs.batched import EnvSpec, StepResult, check_actions
from convoy.envs.layout import treadmill_layout
from convoy.envs.treadmill.config import (
    DX,
    DY,
    LONGITUDINAL,
    N_ACTIONS,
    N_HEADINGS,
    NEIGHBOUR_FEATURES,
    OWN_FEATURES,
    WORD_BITS,
    TreadmillConfig,
)
from convoy.envs.treadmill.drivers import encode16

ACTION_STEER = np.arange(N_ACTIONS, dtype=np.int64) // 3 - 1  # −1 right, 0 straight, +1 left
ACTION_ACCEL = np.arange(N_ACTIONS, dtype=np.int64) % 3 - 1  # −1 brake, 0 keep, +1 accelerate
_ONE_HOT = np.eye(N_HEADINGS, dtype=np.float32)
_UNSEEN = 1 << 40  # a squared distance beyond any window: the sort key of a car not observed
STREAM_BELT, STREAM_BELT_START, STREAM_HEADING = 5, 6, 7  # the varying belt's draws (envs.rng's named streams are 1…4)


def distance(xa, ya, xb, yb) -> np.ndarray:
    """Euclidean distance in cells on the window."""
    return np.sqrt(_square_distance(xa, ya, xb, yb).astype(np.float64))


def _square_distance(xa, ya, xb, yb) -> np.ndarray:
    """Squared distance in cells, exact in integers: it orders cars as ``distance`` does, without a square root."""
    dx = np.asarray(xb) - np.asarray(xa)
    dy = np.asarray(yb) - np.asarray(ya)
    return dx * dx + dy * dy


class TreadmillEngine:
    """B treadmill highways stepped as arrays. Implements ``envs.batched.BatchedEnv``."""

    def __init__(self, config: TreadmillConfig | None = None, num_envs: int = 1, autoreset: bool = True) -> None:
        """``autoreset=False`` leaves finished envs as they ended (single-env front ends reset explicitly)."""
        if num_envs < 1:
            raise ValueError(f"num_envs: must be ≥ 1 (got {num_envs})")
        self.cfg = cfg = config or TreadmillConfig()
        self.num_envs = num_envs
        self.autoreset = autoreset
        self.spec = EnvSpec(
            name="treadmill",
            agent_ids=tuple(f"agent_{i}" for i in range(cfg.n_agents)),
            obs_dims=(cfg.obs_dim,) * cfg.n_agents,
            n_actions=(N_ACTIONS,) * cfg.n_agents,
            max_steps=cfg.max_steps,
            layout=treadmill_layout(cfg),  # what encoder=entity reads the cars from
        )
        n, c = cfg.n_agents, cfg.n_cars
        self._is_agent = np.arange(c) < n
        pair = self._is_agent[:, None] | self._is_agent[None, :]
        # the pairs (i < j) whose collision matters, and which cars each involves: [P, C]
        self._pair_i, self._pair_j = np.nonzero(np.triu(pair, k=1))
        self._pair_cars = np.zeros((len(self._pair_i), c), np.float32)
        self._pair_cars[np.arange(len(self._pair_i)), self._pair_i] = 1.0
        self._pair_cars[np.arange(len(self._pair_i)), self._pair_j] = 1.0
        self._top = np.where(self._is_agent, cfg.max_speed, cfg.adversary_top)  # [C] each car's top speed
        # [C] the fastest each car may steer at (``adversary_steer_speed``; agents always steer)
        self._steer_cap = np.where(self._is_agent, cfg.top_speed, cfg.adversary_steer_cap)
        # [N, C] added to an agent's squared distance to its own car: never its closest, never observed
        self._own_car = np.where(np.eye(n, c, dtype=bool), _UNSEEN, 0)
        self._not_own_car = ~np.eye(n, c, dtype=bool)
        # the sight rule as a table over every offset a car can have from an agent, cars just off the window included
        margin = 2 * (cfg.top_speed + (cfg.treadmill_speed_max or cfg.treadmill_speed)) + 2
        self._reach = (cfg.length + margin, cfg.width + margin)
        self._sight = _sight_table(*self._reach, cfg.sensor_range, cfg.sensor_fov)
        self._rows = np.arange(2 * num_envs) * c  # env e's first car in a flattened [E, C] array (E ≤ 2B)
        # a seen car's slot by (heading, speed): seen flag, offset (filled in per car), heading one-hot, speed; then
        # the empty slot's zeros
        heading, speed = np.divmod(np.arange(N_HEADINGS * (cfg.top_speed + 1)), cfg.top_speed + 1)
        slots = np.zeros((len(heading) + 1, NEIGHBOUR_FEATURES), np.float32)
        slots[:-1, 0] = 1.0
        slots[:-1, 3 : 3 + N_HEADINGS] = _ONE_HOT[heading]
        slots[:-1, 3 + N_HEADINGS] = speed / cfg.top_speed
        self._slot_table = slots
        # every other car of each agent, agents first then adversaries (the full-information layout)
        self._others = np.array([[j for j in range(c) if j != i] for i in range(n)], dtype=np.int64).reshape(n, c - 1)
        shape = (num_envs, c)
        self.x = np.zeros(shape, np.int64)
        self.y = np.zeros(shape, np.int64)
        self.heading = np.zeros(shape, np.int64)
        self.speed = np.zeros(shape, np.int64)
        self.t = np.zeros(num_envs, np.int64)
        self.belt = np.full(num_envs, cfg.treadmill_speed, np.int64)  # cells the belt carries cars back this step
        # which cars crashed in the last step [B, C] (an agent: a collision or leaving the window; an adversary: a
        # collision with an agent): what a study of how episodes end reads (benchmarks/treadmill_causes.py)
        self.last_crashed = np.zeros((num_envs, cfg.n_cars), bool)
        self._varying_belt = cfg.treadmill_speed_max is not None and cfg.treadmill_speed_max > cfg.treadmill_speed
        self._streams = rng.EnvStreams(num_envs)
        self._ep_return = np.zeros((num_envs, n), np.float64)

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in every env; returns obs ``[B, N, D]``.

        ``seed``: an int is expanded per env by ``envs.batched.env_seeds``; an array gives each env its
        seed; None keeps the current streams (fresh entropy on the very first reset).
        """
        self._streams.seed(seed)
        self._spawn(np.arange(self.num_envs))
        self._ep_return[:] = 0.0
        self._streams.advance()
        return self._observe(self.x, self.y, self.heading, self.speed)[0]

    def _spawn(self, envs: np.ndarray) -> None:
        """Place the agents of ``envs`` on distinct lattice cells of the middle half of the window, facing forward;
        the adversaries enter at the front or back as they do during the episode."""
        cfg = self.cfg
        n, m, k = cfg.n_agents, cfg.n_adversaries, cfg.spawn_heading_spread
        first, blocks_x, blocks_y = cfg.spawn_blocks
        n_cells = blocks_x * blocks_y
        u_cells, u_heading, u_belt, u_enter = self._streams.uniforms(
            (rng.STREAM_SPAWN, _distinct_draws(n_cells, n)),
            (STREAM_HEADING, n if k else 0),
            (STREAM_BELT_START, 1 if self._varying_belt else 0),
            (rng.STREAM_ENTER, 2 * m),
            envs=envs,
        )
        cells = _distinct_choice(self._streams, envs, n_cells, n, u_cells)
        half = cfg.spawn_gap // 2
        self.x[envs, :n] = (first + cells // blocks_y) * cfg.spawn_gap + half
        self.y[envs, :n] = (cells % blocks_y) * cfg.spawn_gap + half
        self.heading[envs] = 0
        if k:
            self.heading[envs, :n] = ((u_heading * (2 * k + 1)).astype(np.int64) - k) % N_HEADINGS
        self.speed[envs] = cfg.initial_speed
        self.t[envs] = 0
        if self._varying_belt:
            self.belt[envs] = self._belt_draw(u_belt[:, 0])
        if m:  # headings were set to 0 above
            x, y, speed = self._entry(u_enter)
            self.x[envs, n:], self.y[envs, n:], self.speed[envs, n:] = x, y, speed

    def close(self) -> None:
        """Nothing to release: the engine is plain arrays."""

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray) -> StepResult:
        """Advance all B envs by one step with agent actions ``[B, N]``."""
        cfg = self.cfg
        n = cfg.n_agents
        acts = check_actions(actions, self.num_envs, self.spec.n_actions)
        m = cfg.n_adversaries
        # every draw of this tick in one pass (the counter-based streams make it equal to one draw per purpose)
        u_belt, u_adv, u_enter = self._streams.uniforms(
            (STREAM_BELT, 2 if self._varying_belt else 0), (rng.STREAM_ADVERSARY, 2 * m), (rng.STREAM_ENTER, 2 * m)
        )
        if self._varying_belt:
            self.belt = np.where(u_belt[:, 0] < cfg.treadmill_switch_prob, self._belt_draw(u_belt[:, 1]), self.belt)
        if m:
            acts = np.concatenate([acts, self._adversary_actions(u_adv)], axis=1)
        self.heading = (self.heading + np.where(self.speed <= self._steer_cap, ACTION_STEER[acts], 0)) % N_HEADINGS
        self.speed = np.clip(self.speed + ACTION_ACCEL[acts], 0, self._top)
        crashed, bounced = self._move()
        self.heading[:, n:] = np.where(bounced, (N_HEADINGS - self.heading[:, n:]) % N_HEADINGS, self.heading[:, n:])
        self.x = self.x - self.belt[:, None]
        outside = (self.x < 0) | (self.x >= cfg.length)
        crashed[:, :n] |= outside[:, :n]
        self.last_crashed = crashed
        if m:
            self._reenter(outside[:, n:], u_enter)
        self.t += 1
        self._streams.advance()

        agent_crashed = crashed[:, :n]
        terminated = agent_crashed.any(axis=1)
        truncated = (self.t >= cfg.max_steps) & ~terminated
        length = self.t.copy()
        done = np.flatnonzero(terminated | truncated) if self.autoreset else np.zeros(0, np.int64)
        # The finished envs start again before the one observation pass, which sees every env as it is now (the
        # new episodes) and, in rows B…, the finished envs as they ended (their final observations).
        state = [self.x, self.y, self.heading, self.speed]
        if done.size:
            ended = [a[done] for a in state]
            self._spawn(done)
            state = [np.concatenate([a, b]) for a, b in zip(state, ended, strict=True)]
        observed, closest = self._observe(*state)
        obs = final_obs = observed[: self.num_envs]
        if done.size:
            final_obs = obs.copy()
            final_obs[done] = observed[self.num_envs :]
            closest, ended_closest = closest[: self.num_envs].copy(), closest[self.num_envs :]
            closest[done] = ended_closest
        reward = np.where(
            agent_crashed, -cfg.crash_penalty, np.minimum(closest, cfg.reward_distance_cap) / cfg.reward_distance_cap
        ).astype(np.float32)
        self._ep_return += reward
        info = {"crashed": agent_crashed, "episode_length": length, "episode_return": self._ep_return.copy()}
        self._ep_return[done] = 0.0
        return StepResult(obs, reward, np.asarray(terminated), truncated, final_obs, info)

    def _adversary_actions(self, u: np.ndarray) -> np.ndarray:
        """Chase the closest agent with probability ``aggression``, else act uniformly at random (``u [B, 2M]``:
        this tick's uniforms of the adversary stream). Squared distances pick the same cars as distances."""
        cfg = self.cfg
        n = cfg.n_agents
        ax, ay, ah, av = self.x[:, n:], self.y[:, n:], self.heading[:, n:], self.speed[:, n:]
        gx, gy = self.x[:, None, :n], self.y[:, None, :n]
        target = np.argmin(_square_distance(ax[..., None], ay[..., None], gx, gy), axis=-1)  # [B, M]
        flat = target + self._rows[: len(target), None]
        tx = self.x.ravel()[flat][..., None]
        ty = self.y.ravel()[flat][..., None]
        steers = (av <= self._steer_cap[n:])[..., None]  # a chaser too fast to steer keeps its heading
        h = (ah[..., None] + np.where(steers, ACTION_STEER, 0)) % N_HEADINGS  # [B, M, 9] outcome of each action
        v = np.clip(av[..., None] + ACTION_ACCEL, 0, cfg.adversary_top)
        cx = ax[..., None] + v * DX[h] - self.belt[:, None, None]
        cy = np.clip(ay[..., None] + v * DY[h], 0, cfg.width - 1)
        greedy = np.argmin(_square_distance(cx, cy, tx, ty), axis=-1)
        coin, pick = u[:, : cfg.n_adversaries], u[:, cfg.n_adversaries :]
        random_action = (pick * N_ACTIONS).astype(np.int64)
        return np.where(coin < cfg.aggression, greedy, random_action)

    def _belt_draw(self, u: np.ndarray) -> np.ndarray:
        """A belt speed in treadmill_speed … treadmill_speed_max, uniform, from uniforms ``u`` in [0, 1)."""
        lo, hi = self.cfg.treadmill_speed, self.cfg.treadmill_speed_max
        assert hi is not None  # only a varying belt draws
        return lo + (u * (hi - lo + 1)).astype(np.int64)

    def _entry(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where adversaries enter, from uniforms ``u [E, 2M]`` of the enter stream: (x, y, speed) ``[E, M]`` —
        from the back at top speed or from the front at speed 0, at a random lateral position."""
        cfg = self.cfg
        m = cfg.n_adversaries
        from_back = u[:, :m] < 0.5
        lane = np.minimum((u[:, m:] * cfg.width).astype(np.int64), cfg.width - 1)
        return np.where(from_back, 0, cfg.length - 1), lane, np.where(from_back, cfg.adversary_top, 0)

    def _reenter(self, out: np.ndarray, u: np.ndarray) -> None:
        """Adversaries ``out [B, M]`` that left at the front or back come back in (``_entry``), facing forward."""
        if not out.any():
            return
        x, y, speed = self._entry(u)
        adv = np.s_[:, self.cfg.n_agents :]
        self.x[adv] = np.where(out, x, self.x[adv])
        self.y[adv] = np.where(out, y, self.y[adv])
        self.heading[adv] = np.where(out, 0, self.heading[adv])
        self.speed[adv] = np.where(out, speed, self.speed[adv])

    def _move(self) -> tuple[np.ndarray, np.ndarray]:
        """Move every car by its speed in micro-steps; returns (crashed [B, C], adversary bounced [B, M])."""
        cfg = self.cfg
        n, width = cfg.n_agents, cfg.width
        dx, dy = DX[self.heading], DY[self.heading]
        x, y = self.x, self.y
        crashed = np.zeros(x.shape, bool)
        bounced = np.zeros((x.shape[0], cfg.n_adversaries), bool)
        for k in range(1, cfg.top_speed + 1):
            moving = (self.speed >= k) & ~crashed
            if not moving.any():
                break
            mx, my = dx * moving, dy * moving
            nx, ny = x + mx, y + my
            off = (ny < 0) | (ny >= width)
            bounced |= off[:, n:]
            ny[:, n:] = np.clip(ny[:, n:], 0, width - 1)
            my[:, n:] = ny[:, n:] - y[:, n:]
            crashed[:, :n] |= off[:, :n]
            # Cells are keyed on a (width + 2)-wide grid so that off-road y = −1 or width stay distinct;
            # midpoints of moves are compared on the doubled grid: equal midpoints = swap or crossing.
            cell = nx * (width + 2) + (ny + 1)
            mid = (2 * x + mx) * (2 * width + 4) + (2 * y + my + 2)
            i, j = self._pair_i, self._pair_j
            hit = (np.take(cell, i, axis=1) == np.take(cell, j, axis=1)) | (
                np.take(mid, i, axis=1) == np.take(mid, j, axis=1)
            )
            crashed |= hit.astype(np.float32) @ self._pair_cars > 0  # [B, P] hits → [B, C] cars in one
            x, y = nx, ny
        self.x, self.y = x, y
        return crashed, bounced

    # ------------------------------------------------------------ observation
    def offsets(self, envs: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Offsets in cells ``[E, N, C]`` from each agent to every car (its own car included, at 0)."""
        return self._offsets(self.x[envs], self.y[envs])

    def _offsets(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.cfg.n_agents
        return x[:, None, :] - x[:, :n, None], y[:, None, :] - y[:, :n, None]

    def visible(self, rel_x: np.ndarray, rel_y: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Which cars at offsets ``[..., N, C]`` an agent with ``heading [..., N]`` senses: within ``sensor_range``
        and inside its field of view (``sensor_fov`` degrees, centred on the heading). Read from ``_sight_table``,
        the rule evaluated once for every offset the window allows (the rule itself where an offset falls outside)."""
        cfg = self.cfg
        (rx, ry), table = self._reach, self._sight
        if table is None or np.abs(rel_x).max(initial=0) > rx or np.abs(rel_y).max(initial=0) > ry:
            return _in_sight(rel_x, rel_y, heading, cfg.sensor_range, cfg.sensor_fov)
        ny = 2 * ry + 1
        base = (heading * (2 * rx + 1) + rx) * ny + ry  # [..., N] the flat index of offset (0, 0)
        return table[base[..., None] + rel_x * ny + rel_y]

    def sees(self, rel_x: np.ndarray, rel_y: np.ndarray, heading: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """``visible`` less, with ``adversary_stealth``, each adversary for the agent it chases (its closest agent:
        ``dist [E, N, C]``, the agents' distances, or squared distances, to every car)."""
        ok = self.visible(rel_x, rel_y, heading)
        if self.cfg.adversary_stealth and self.cfg.n_adversaries:
            n = self.cfg.n_agents
            target = np.argmin(dist[:, :, n:], axis=1)  # [E, M] the agent each adversary chases
            ok[:, :, n:] &= target[:, None, :] != np.arange(n)[None, :, None]
        return ok

    def nearest(self, envs: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the ``observe_k`` cars each agent observes ``[E, N, k]``, their distances — inf for an empty slot —, and
        each agent's distance to its closest car, seen or not ``[E, N]``)."""
        return self._nearest(self.heading[envs], *self.offsets(envs))

    def _nearest(self, heading, rel_x, rel_y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``nearest`` from the offsets. Cars are ordered by squared distance, then index (the order of a stable
        sort of distances), as one integer key per car: a sort of keys instead of an argsort and gathers."""
        cfg = self.cfg
        n, k, c = cfg.n_agents, cfg.observe_k, cfg.n_cars
        d2 = rel_x * rel_x + rel_y * rel_y  # [E, N, C], exact
        closest = np.sqrt((d2 + self._own_car).min(axis=2).astype(np.float64))
        seen = self.sees(rel_x, rel_y, heading[:, :n], d2) & self._not_own_car
        bits = max(1, (c - 1).bit_length())  # the car's index in a key's low bits
        key = (np.where(seen, d2, _UNSEEN) << bits) | np.arange(c)
        key = key.min(axis=2, keepdims=True) if k == 1 else np.sort(key, axis=2)[..., :k]
        near, near_d2 = key & ((1 << bits) - 1), key >> bits
        near_dist = np.where(near_d2 < _UNSEEN, np.sqrt(near_d2.astype(np.float64)), np.inf)
        return near, near_dist, closest

    def team_observed(self, near: np.ndarray, near_dist: np.ndarray) -> np.ndarray:
        """``[E, C]``: which cars some agent observes (what the team as a whole could tell each other)."""
        return ((near[..., None] == np.arange(self.cfg.n_cars)) & np.isfinite(near_dist)[..., None]).any(axis=(1, 2))

    def observe(self, envs: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Observations ``[E, N, D]`` of ``envs`` as they are now and each agent's distance to its closest car."""
        return self._observe(self.x[envs], self.y[envs], self.heading[envs], self.speed[envs])

    def _observe(self, x: np.ndarray, y: np.ndarray, h: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observations ``[E, N, D]`` of E highways in state (x, y, heading, speed) ``[E, C]`` and each agent's
        distance to its closest car. Written part by part into one array, in ``envs.layout.treadmill_layout``'s
        order."""
        cfg = self.cfg
        n, k = cfg.n_agents, cfg.observe_k
        e = len(x)
        rel_x, rel_y = self._offsets(x, y)
        near, near_dist, closest = self._nearest(h, rel_x, rel_y)
        obs = np.empty((e, n, cfg.obs_dim), np.float32)

        w1, l1 = float(cfg.width - 1), float(cfg.length - 1)
        own_y = y[:, :n].astype(np.float32)
        obs[..., 0] = 2.0 * own_y / w1 - 1.0
        obs[..., 1 : 1 + N_HEADINGS] = _ONE_HOT[h[:, :n]]
        obs[..., 1 + N_HEADINGS] = v[:, :n] / cfg.max_speed
        obs[..., 2 + N_HEADINGS] = own_y / w1
        obs[..., 3 + N_HEADINGS] = (w1 - own_y) / w1
        obs[..., LONGITUDINAL] = 2.0 * x[:, :n] / l1 - 1.0

        flat = near + self._rows[:e, None, None]  # [E, N, k] the observed cars in x.ravel() and alike
        seen = np.isfinite(near_dist)
        # a slot's features but its offset, a row of _slot_table by the car's heading and speed (an empty slot: zeros)
        slot = np.where(seen, (h * (cfg.top_speed + 1) + v).ravel()[flat], len(self._slot_table) - 1)
        neighbour = np.take(self._slot_table, slot, axis=0)  # [E, N, k, F]
        r, seen_f = np.float32(cfg.sensor_range), seen.astype(np.float32)
        neighbour[..., 1] = ((x.ravel()[flat] - x[:, :n, None]) / r).astype(np.float32) * seen_f
        neighbour[..., 2] = ((y.ravel()[flat] - y[:, :n, None]) / r).astype(np.float32) * seen_f
        private = OWN_FEATURES + k * NEIGHBOUR_FEATURES
        obs[..., OWN_FEATURES:private] = neighbour.reshape(e, n, -1)
        col = private
        if cfg.team_observations:  # each teammate's private observation, teammates in index order
            col = _put(obs, col, obs[:, self._others[:, : n - 1], :private].reshape(e, n, -1))
        if cfg.full_information:
            me, o = np.arange(n)[:, None], self._others  # [N, 1], [N, C−1]
            speed = v[:, o] / cfg.top_speed  # [E, N, C−1]
            adversary = np.broadcast_to(o >= n, speed.shape)
            full = np.stack([rel_x[:, me, o] / l1, rel_y[:, me, o] / w1, speed, adversary], axis=3, dtype=np.float32)
            col = _put(obs, col, full.reshape(e, n, -1))
        if cfg.team_sightings:
            col = _put(obs, col, self._team_sightings(self.team_observed(near, near_dist), rel_x, rel_y, v, h))
        np.clip(obs[..., :col], -1.0, 1.0, out=obs[..., :col])
        if cfg.team_words:  # bits, nothing to clip
            col = _put(obs, col, self._team_words(obs[..., :col]))
        assert col == cfg.obs_dim
        return obs, closest

    def _team_words(self, obs: np.ndarray) -> np.ndarray:
        """``[E, N, (N−1)·16]``: each teammate's 16-bit word (``drivers.encode16`` of its observation, as the
        team16 references compute it), as bits, teammates in index order."""
        n = self.cfg.n_agents
        words = encode16(obs, self.cfg).astype(np.int64)  # [E, N]
        bits = ((words[..., None] >> np.arange(WORD_BITS)) & 1).astype(np.float32)  # [E, N, 16]
        return bits[:, self._others[:, : n - 1]].reshape(len(obs), n, -1)

    def _team_sightings(self, observed, rel_x, rel_y, speed, heading) -> np.ndarray:
        """``[E, N, (C−1)·F]``: each other car that a teammate is (its position it can say) or that some agent
        observes, in the agent's own frame — known flag, offset / sensor range, speed, adversary flag, then with
        ``sighting_headings`` its heading one-hot; zeros if unknown. The offsets share the scale of the agent's own
        neighbour slots: a car 10 cells behind reads the same whether the agent sees it or a teammate tells it (over
        the road's size it read 0.1, six times smaller)."""
        cfg = self.cfg
        n, o = cfg.n_agents, self._others
        known = observed[:, o] | (o < n)  # [E, N, C−1]
        me = np.arange(n)[:, None]
        r = np.float32(cfg.sensor_range)
        adversary = np.broadcast_to(o >= n, known.shape)
        feats = [known, rel_x[:, me, o] / r, rel_y[:, me, o] / r, speed[:, o] / cfg.top_speed, adversary]
        out = np.stack(feats, axis=3, dtype=np.float32)
        if cfg.sighting_headings:
            out = np.concatenate([out, _ONE_HOT[heading[:, o]]], axis=3)  # [E, N, C−1, headings]
        out = out * known[..., None]
        return out.reshape(len(observed), n, -1)


def _in_sight(rel_x: np.ndarray, rel_y: np.ndarray, heading: np.ndarray, sensor_range: float, fov: float) -> np.ndarray:
    """``TreadmillEngine.visible``'s rule, computed."""
    ok = rel_x * rel_x + rel_y * rel_y <= sensor_range**2
    if fov < 360:
        along = rel_x * DX[heading][..., None] + rel_y * DY[heading][..., None]
        norm = np.sqrt((rel_x * rel_x + rel_y * rel_y) * (DX[heading] ** 2 + DY[heading] ** 2)[..., None])
        ok &= along >= np.cos(np.radians(fov / 2)) * norm - 1e-9
    return ok


@functools.cache
def _sight_table(rx: int, ry: int, sensor_range: float, fov: float) -> np.ndarray | None:
    """``_in_sight`` for every heading and offset up to (rx, ry), flattened (heading, offset along, across): a lookup
    replaces ~10 array operations per observation. None for a huge window (the rule is computed instead)."""
    if N_HEADINGS * (2 * rx + 1) * (2 * ry + 1) > 1 << 23:
        return None
    ox, oy = np.meshgrid(np.arange(-rx, rx + 1), np.arange(-ry, ry + 1), indexing="ij")
    shape = (N_HEADINGS, 1, ox.size)  # the rule's [..., N, C] offsets against [..., N] headings
    rel_x, rel_y = (np.broadcast_to(o.reshape(-1), shape) for o in (ox, oy))
    table = _in_sight(rel_x, rel_y, np.arange(N_HEADINGS)[:, None], sensor_range, fov).reshape(-1)
    table.flags.writeable = False  # shared by every engine of this geometry
    return table


def _put(obs: np.ndarray, col: int, part: np.ndarray) -> int:
    """Write ``part [E, N, F]`` into ``obs`` from column ``col``; returns the next free column."""
    obs[..., col : col + part.shape[-1]] = part
    return col + part.shape[-1]


def _distinct_draws(n_items: int, k: int) -> int:
    """How many uniforms of the spawn stream ``_distinct_choice`` starts from."""
    return n_items if 2 * k > n_items else k


def _distinct_choice(streams: rng.EnvStreams, envs: np.ndarray, n_items: int, k: int, u: np.ndarray) -> np.ndarray:
    """k distinct integers in [0, n_items) per env, drawn from that env's own stream only (``u``: its first
    ``_distinct_draws`` uniforms of the spawn stream)."""
    if 2 * k > n_items:  # dense: a random permutation's prefix
        return np.argsort(u, axis=1, kind="stable")[:, :k]
    # sparse: draw k, redraw the duplicates with fresh counters until none remain
    out = (u * n_items).astype(np.int64)
    for round_ in range(1, 10_000):
        order = np.argsort(out, axis=1, kind="stable")
        srt = np.take_along_axis(out, order, axis=1)
        dup_sorted = np.zeros_like(out, dtype=bool)
        dup_sorted[:, 1:] = srt[:, 1:] == srt[:, :-1]
        if not dup_sorted.any():
            return out
        dup = np.zeros_like(dup_sorted)
        np.put_along_axis(dup, order, dup_sorted, axis=1)
        fresh = streams.uniform(rng.STREAM_SPAWN + round_ * 7919, k, envs)
        out = np.where(dup, (fresh * n_items).astype(np.int64), out)
    raise RuntimeError("could not place cars on distinct cells")  # unreachable for 2k ≤ n_items
