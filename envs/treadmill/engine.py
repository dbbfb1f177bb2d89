"""The one treadmill physics: B highways × C cars stepped together with numpy.

Geometry. A ``length × width`` grid of cells; x runs along the road and wraps (a torus), y runs
across it and is bounded (0 … width−1). Each car has a cell (x, y), a heading h ∈ 0…7 (h = 0
drives forward along +x, each step of h turns 45° to the left, towards +y) and a speed
v ∈ 0…max_speed cells per step. The treadmill carries every car ``treadmill_speed`` cells back
per step, so a car driving forward at that speed holds its place on the picture.

Actions. 9 per car: (steer −45°, 0, +45°) × (decelerate, keep, accelerate), index
``3 * steer_index + accel_index``. Cars 0…N−1 are the agents; N…N+M−1 are adversaries that
each step, with probability ``aggression``, take the action whose one-step outcome lands
closest to the nearest agent, else a uniformly random action.

Motion and collisions. A step is split into ``max_speed`` micro-steps; a car with speed v moves
one cell along its heading in each of the first v micro-steps. After every micro-step two cars
collide if they share a cell, or if their moves crossed (a swap, or two diagonals through the same
point: equal move midpoints). A crashed car stops where it is (a wreck others can hit). An agent
that leaves the road sideways crashes; adversaries bounce off the road edge (their y is clamped
and their heading mirrored), and collisions between two adversaries are ignored.

Rewards and episodes. Per agent and step, ``min(d, d_max) / d_max`` ∈ [0, 1] where d is the
Euclidean (torus-aware) distance in cells to the closest other car; a crashed agent gets
``−crash_penalty`` instead. Any agent crash terminates the episode for all; otherwise it is
truncated after ``max_steps``. Finished envs reset themselves (see ``envs.batched``).

Observation per agent (all features clipped to [−1, 1]): lateral position, heading one-hot,
speed / max_speed, distance to each road edge / (width−1); then for each of the ``observe_k``
closest cars (agents and adversaries alike, as in the paper): relative position (torus-aware,
/ (length/2) and / (width−1)), heading one-hot and speed. Cars spawn forward-facing at
``initial_speed`` on random distinct cells of a lattice of pitch ``spawn_gap``.

Randomness comes from ``envs.rng``: draws depend only on the env's own seed and step
counter, so a batch equals its envs stepped one by one, bit for bit (seed env b alone with
``envs.batched.env_seeds(s, B)[b]`` to replay env b of a batch seeded s).
"""

from __future__ import annotations

import numpy as np

from envs import rng
from envs.batched import EnvSpec, StepResult, check_actions
from envs.treadmill.config import N_ACTIONS, N_HEADINGS, TreadmillConfig

# Unit move per heading, counter-clockwise from "forward along the road".
DX = np.array([1, 1, 0, -1, -1, -1, 0, 1], dtype=np.int64)
DY = np.array([0, 1, 1, 1, 0, -1, -1, -1], dtype=np.int64)
ACTION_STEER = np.arange(N_ACTIONS, dtype=np.int64) // 3 - 1  # −1 right, 0 straight, +1 left
ACTION_ACCEL = np.arange(N_ACTIONS, dtype=np.int64) % 3 - 1  # −1 brake, 0 keep, +1 accelerate
_ONE_HOT = np.eye(N_HEADINGS, dtype=np.float32)


def torus_delta(a: np.ndarray, b: np.ndarray, length: int) -> np.ndarray:
    """Signed offset from a to b along a wrapping axis, in [−length/2, length/2)."""
    return (b - a + length // 2) % length - length // 2


def torus_distance(xa, ya, xb, yb, length: int) -> np.ndarray:
    """Euclidean distance in cells on the road, wrapping along its length."""
    dx = torus_delta(np.asarray(xa), np.asarray(xb), length)
    dy = np.asarray(yb) - np.asarray(ya)
    return np.sqrt((dx * dx + dy * dy).astype(np.float64))


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
        )
        n, c = cfg.n_agents, cfg.n_cars
        self._is_agent = np.arange(c) < n
        pair = self._is_agent[:, None] | self._is_agent[None, :]
        self._counted_pair = pair & ~np.eye(c, dtype=bool)  # pairs whose collision matters
        self._self_mask = np.where(np.eye(n, c, dtype=bool), np.inf, 0.0)  # excludes an agent's own car
        shape = (num_envs, c)
        self.x = np.zeros(shape, np.int64)
        self.y = np.zeros(shape, np.int64)
        self.heading = np.zeros(shape, np.int64)
        self.speed = np.zeros(shape, np.int64)
        self.t = np.zeros(num_envs, np.int64)
        self._streams = rng.EnvStreams(num_envs)
        self._ep_return = np.zeros((num_envs, n), np.float64)

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | np.ndarray | None = None) -> np.ndarray:
        """Start new episodes in every env; returns obs ``[B, N, D]``.

        ``seed``: an int is expanded per env by ``envs.batched.env_seeds``; an array gives each env its
        seed; None keeps the current streams (fresh entropy on the very first reset).
        """
        self._streams.seed(seed)
        everyone = np.arange(self.num_envs)
        self._spawn(everyone)
        self._streams.advance()
        return self._observe(everyone)[0]

    def _spawn(self, envs: np.ndarray) -> None:
        """Place every car of ``envs`` on distinct lattice cells, facing forward."""
        cfg = self.cfg
        blocks_x, blocks_y = cfg.length // cfg.spawn_gap, cfg.width // cfg.spawn_gap
        cells = _distinct_choice(self._streams, envs, blocks_x * blocks_y, cfg.n_cars)
        half = cfg.spawn_gap // 2
        self.x[envs] = (cells // blocks_y) * cfg.spawn_gap + half
        self.y[envs] = (cells % blocks_y) * cfg.spawn_gap + half
        self.heading[envs] = 0
        self.speed[envs] = cfg.initial_speed
        self.t[envs] = 0
        self._ep_return[envs] = 0.0

    def close(self) -> None:
        """Nothing to release: the engine is plain arrays."""

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray) -> StepResult:
        """Advance all B envs by one step with agent actions ``[B, N]``."""
        cfg = self.cfg
        n = cfg.n_agents
        acts = check_actions(actions, self.num_envs, self.spec.n_actions)
        if cfg.n_adversaries:
            acts = np.concatenate([acts, self._adversary_actions()], axis=1)
        self.heading = (self.heading + ACTION_STEER[acts]) % N_HEADINGS
        self.speed = np.clip(self.speed + ACTION_ACCEL[acts], 0, cfg.max_speed)
        crashed, bounced = self._move()
        self.heading[:, n:] = np.where(bounced, (N_HEADINGS - self.heading[:, n:]) % N_HEADINGS, self.heading[:, n:])
        self.x = (self.x - cfg.treadmill_speed) % cfg.length
        self.t += 1
        self._streams.advance()

        everyone = np.arange(self.num_envs)
        final_obs, closest = self._observe(everyone)
        agent_crashed = crashed[:, :n]
        reward = np.where(
            agent_crashed, -cfg.crash_penalty, np.minimum(closest, cfg.reward_distance_cap) / cfg.reward_distance_cap
        ).astype(np.float32)
        terminated = agent_crashed.any(axis=1)
        truncated = (self.t >= cfg.max_steps) & ~terminated
        self._ep_return += reward
        info = {"crashed": agent_crashed, "episode_length": self.t.copy(), "episode_return": self._ep_return.copy()}

        done = np.flatnonzero(terminated | truncated)
        obs = final_obs
        if done.size and self.autoreset:
            obs = final_obs.copy()
            self._spawn(done)
            obs[done] = self._observe(done)[0]
        return StepResult(obs, reward, terminated, truncated, final_obs, info)

    def _adversary_actions(self) -> np.ndarray:
        """Chase the closest agent with probability ``aggression``, else act uniformly at random."""
        cfg = self.cfg
        n = cfg.n_agents
        ax, ay, ah, av = self.x[:, n:], self.y[:, n:], self.heading[:, n:], self.speed[:, n:]
        gx, gy = self.x[:, None, :n], self.y[:, None, :n]
        target = np.argmin(torus_distance(ax[..., None], ay[..., None], gx, gy, cfg.length), axis=-1)  # [B, M]
        tx = np.take_along_axis(self.x[:, :n], target, axis=1)[..., None]
        ty = np.take_along_axis(self.y[:, :n], target, axis=1)[..., None]
        h = (ah[..., None] + ACTION_STEER) % N_HEADINGS  # [B, M, 9] outcome of each action
        v = np.clip(av[..., None] + ACTION_ACCEL, 0, cfg.max_speed)
        cx = ax[..., None] + v * DX[h]
        cy = np.clip(ay[..., None] + v * DY[h], 0, cfg.width - 1)
        greedy = np.argmin(torus_distance(cx, cy, tx, ty, cfg.length), axis=-1)
        u = self._streams.uniform(rng.STREAM_ADVERSARY, 2 * cfg.n_adversaries)
        coin, pick = u[:, : cfg.n_adversaries], u[:, cfg.n_adversaries :]
        random_action = (pick * N_ACTIONS).astype(np.int64)
        return np.where(coin < cfg.aggression, greedy, random_action)

    def _move(self) -> tuple[np.ndarray, np.ndarray]:
        """Move every car by its speed in micro-steps; returns (crashed [B, C], adversary bounced [B, M])."""
        cfg = self.cfg
        n, length, width = cfg.n_agents, cfg.length, cfg.width
        dx, dy = DX[self.heading], DY[self.heading]
        x, y = self.x, self.y
        crashed = np.zeros(x.shape, bool)
        bounced = np.zeros((x.shape[0], cfg.n_adversaries), bool)
        for k in range(1, cfg.max_speed + 1):
            moving = (self.speed >= k) & ~crashed
            if not moving.any():
                break
            mx, my = dx * moving, dy * moving
            nx, ny = (x + mx) % length, y + my
            off = (ny < 0) | (ny >= width)
            bounced |= off[:, n:]
            ny[:, n:] = np.clip(ny[:, n:], 0, width - 1)
            my[:, n:] = ny[:, n:] - y[:, n:]
            crashed[:, :n] |= off[:, :n]
            # Cells are keyed on a (width + 2)-wide grid so that off-road y = −1 or width stay distinct;
            # midpoints of moves are compared on the doubled grid: equal midpoints = swap or crossing.
            cell = nx * (width + 2) + (ny + 1)
            mid = ((2 * x + mx) % (2 * length)) * (2 * width + 4) + (2 * y + my + 2)
            hit = (cell[:, :, None] == cell[:, None, :]) | (mid[:, :, None] == mid[:, None, :])
            crashed |= (hit & self._counted_pair).any(axis=2)
            x, y = nx, ny
        self.x, self.y = x, y
        return crashed, bounced

    # ------------------------------------------------------------ observation
    def _observe(self, envs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observations ``[len(envs), N, D]`` and each agent's distance to its closest car."""
        cfg = self.cfg
        n, k = cfg.n_agents, cfg.observe_k
        x, y, h, v = self.x[envs], self.y[envs], self.heading[envs], self.speed[envs]
        rel_x = torus_delta(x[:, :n, None], x[:, None, :], cfg.length)  # [E, N, C]
        rel_y = y[:, None, :] - y[:, :n, None]
        dist = np.sqrt((rel_x * rel_x + rel_y * rel_y).astype(np.float64)) + self._self_mask
        near = np.argmin(dist, axis=2)[..., None] if k == 1 else np.argsort(dist, axis=2, kind="stable")[..., :k]
        closest = np.take_along_axis(dist, near[..., :1], axis=2)[..., 0]

        w1 = float(cfg.width - 1)
        own_y = y[:, :n].astype(np.float32)
        own = [
            (2.0 * own_y / w1 - 1.0)[..., None],
            _ONE_HOT[h[:, :n]],
            (v[:, :n] / cfg.max_speed).astype(np.float32)[..., None],
            (own_y / w1)[..., None],
            ((w1 - own_y) / w1)[..., None],
        ]
        nh = np.take_along_axis(h[:, None, :].repeat(n, axis=1), near, axis=2)
        nv = np.take_along_axis(v[:, None, :].repeat(n, axis=1), near, axis=2)
        neighbour = np.concatenate(
            [
                (np.take_along_axis(rel_x, near, axis=2) / (cfg.length / 2)).astype(np.float32)[..., None],
                (np.take_along_axis(rel_y, near, axis=2) / w1).astype(np.float32)[..., None],
                _ONE_HOT[nh],
                (nv / cfg.max_speed).astype(np.float32)[..., None],
            ],
            axis=3,
        ).reshape(len(envs), n, -1)
        obs = np.concatenate([*own, neighbour], axis=2)
        np.clip(obs, -1.0, 1.0, out=obs)
        return obs, closest


def _distinct_choice(streams: rng.EnvStreams, envs: np.ndarray, n_items: int, k: int) -> np.ndarray:
    """k distinct integers in [0, n_items) per env, drawn from that env's own stream only."""
    if 2 * k > n_items:  # dense: a random permutation's prefix
        u = streams.uniform(rng.STREAM_SPAWN, n_items, envs)
        return np.argsort(u, axis=1, kind="stable")[:, :k]
    # sparse: draw k, redraw the duplicates with fresh counters until none remain
    u = streams.uniform(rng.STREAM_SPAWN, k, envs)
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
