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

import numpy as np

from convoy.envs import rng
from convoy.envs.batched import EnvSpec, StepResult, check_actions
from convoy.envs.layout import treadmill_layout
from convoy.envs.treadmill.config import DX, DY, N_ACTIONS, N_HEADINGS, WORD_BITS, TreadmillConfig
from convoy.envs.treadmill.drivers import encode16

ACTION_STEER = np.arange(N_ACTIONS, dtype=np.int64) // 3 - 1  # −1 right, 0 straight, +1 left
ACTION_ACCEL = np.arange(N_ACTIONS, dtype=np.int64) % 3 - 1  # −1 brake, 0 keep, +1 accelerate
_ONE_HOT = np.eye(N_HEADINGS, dtype=np.float32)
STREAM_BELT, STREAM_BELT_START, STREAM_HEADING = 5, 6, 7  # the varying belt's draws (envs.rng's named streams are 1…4)


def distance(xa, ya, xb, yb) -> np.ndarray:
    """Euclidean distance in cells on the window."""
    dx = np.asarray(xb) - np.asarray(xa)
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
            layout=treadmill_layout(cfg),  # what encoder=entity reads the cars from
        )
        n, c = cfg.n_agents, cfg.n_cars
        self._is_agent = np.arange(c) < n
        pair = self._is_agent[:, None] | self._is_agent[None, :]
        self._counted_pair = pair & ~np.eye(c, dtype=bool)  # pairs whose collision matters
        self._top = np.where(self._is_agent, cfg.max_speed, cfg.adversary_top)  # [C] each car's top speed
        # [C] the fastest each car may steer at (``adversary_steer_speed``; agents always steer)
        self._steer_cap = np.where(self._is_agent, cfg.top_speed, cfg.adversary_steer_cap)
        self._self_mask = np.where(np.eye(n, c, dtype=bool), np.inf, 0.0)  # excludes an agent's own car
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
        everyone = np.arange(self.num_envs)
        self._spawn(everyone)
        self._streams.advance()
        return self._observe(everyone)[0]

    def _spawn(self, envs: np.ndarray) -> None:
        """Place the agents of ``envs`` on distinct lattice cells of the middle half of the window, facing forward;
        the adversaries enter at the front or back as they do during the episode."""
        cfg = self.cfg
        n = cfg.n_agents
        first, blocks_x, blocks_y = cfg.spawn_blocks
        cells = _distinct_choice(self._streams, envs, blocks_x * blocks_y, n)
        half = cfg.spawn_gap // 2
        self.x[envs, :n] = (first + cells // blocks_y) * cfg.spawn_gap + half
        self.y[envs, :n] = (cells % blocks_y) * cfg.spawn_gap + half
        self.heading[envs] = 0
        if cfg.spawn_heading_spread:
            k = cfg.spawn_heading_spread
            u = self._streams.uniform(STREAM_HEADING, n, envs)
            self.heading[envs, :n] = ((u * (2 * k + 1)).astype(np.int64) - k) % N_HEADINGS
        self.speed[envs] = cfg.initial_speed
        self.t[envs] = 0
        self._ep_return[envs] = 0.0
        if self._varying_belt:
            self.belt[envs] = self._belt_draw(self._streams.uniform(STREAM_BELT_START, 1, envs)[:, 0])
        if cfg.n_adversaries:
            everyone = np.zeros((self.num_envs, cfg.n_adversaries), bool)
            everyone[envs] = True
            self._reenter(everyone)

    def close(self) -> None:
        """Nothing to release: the engine is plain arrays."""

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray) -> StepResult:
        """Advance all B envs by one step with agent actions ``[B, N]``."""
        cfg = self.cfg
        n = cfg.n_agents
        acts = check_actions(actions, self.num_envs, self.spec.n_actions)
        if self._varying_belt:
            u = self._streams.uniform(STREAM_BELT, 2)
            self.belt = np.where(u[:, 0] < cfg.treadmill_switch_prob, self._belt_draw(u[:, 1]), self.belt)
        if cfg.n_adversaries:
            acts = np.concatenate([acts, self._adversary_actions()], axis=1)
        self.heading = (self.heading + np.where(self.speed <= self._steer_cap, ACTION_STEER[acts], 0)) % N_HEADINGS
        self.speed = np.clip(self.speed + ACTION_ACCEL[acts], 0, self._top)
        crashed, bounced = self._move()
        self.heading[:, n:] = np.where(bounced, (N_HEADINGS - self.heading[:, n:]) % N_HEADINGS, self.heading[:, n:])
        self.x = self.x - self.belt[:, None]
        outside = (self.x < 0) | (self.x >= cfg.length)
        crashed[:, :n] |= outside[:, :n]
        self.last_crashed = crashed
        if cfg.n_adversaries:
            self._reenter(outside[:, n:])
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
        return StepResult(obs, reward, np.asarray(terminated), truncated, final_obs, info)

    def _adversary_actions(self) -> np.ndarray:
        """Chase the closest agent with probability ``aggression``, else act uniformly at random."""
        cfg = self.cfg
        n = cfg.n_agents
        ax, ay, ah, av = self.x[:, n:], self.y[:, n:], self.heading[:, n:], self.speed[:, n:]
        gx, gy = self.x[:, None, :n], self.y[:, None, :n]
        target = np.argmin(distance(ax[..., None], ay[..., None], gx, gy), axis=-1)  # [B, M]
        tx = np.take_along_axis(self.x[:, :n], target, axis=1)[..., None]
        ty = np.take_along_axis(self.y[:, :n], target, axis=1)[..., None]
        steers = (av <= self._steer_cap[n:])[..., None]  # a chaser too fast to steer keeps its heading
        h = (ah[..., None] + np.where(steers, ACTION_STEER, 0)) % N_HEADINGS  # [B, M, 9] outcome of each action
        v = np.clip(av[..., None] + ACTION_ACCEL, 0, cfg.adversary_top)
        cx = ax[..., None] + v * DX[h] - self.belt[:, None, None]
        cy = np.clip(ay[..., None] + v * DY[h], 0, cfg.width - 1)
        greedy = np.argmin(distance(cx, cy, tx, ty), axis=-1)
        u = self._streams.uniform(rng.STREAM_ADVERSARY, 2 * cfg.n_adversaries)
        coin, pick = u[:, : cfg.n_adversaries], u[:, cfg.n_adversaries :]
        random_action = (pick * N_ACTIONS).astype(np.int64)
        return np.where(coin < cfg.aggression, greedy, random_action)

    def _belt_draw(self, u: np.ndarray) -> np.ndarray:
        """A belt speed in treadmill_speed … treadmill_speed_max, uniform, from uniforms ``u`` in [0, 1)."""
        lo, hi = self.cfg.treadmill_speed, self.cfg.treadmill_speed_max
        assert hi is not None  # only a varying belt draws
        return lo + (u * (hi - lo + 1)).astype(np.int64)

    def _reenter(self, out: np.ndarray) -> None:
        """Adversaries ``out [B, M]`` that left at the front or back come back in: from the back at top speed or
        from the front at speed 0, at a random lateral position, facing forward."""
        if not out.any():
            return
        cfg = self.cfg
        m = cfg.n_adversaries
        u = self._streams.uniform(rng.STREAM_ENTER, 2 * m)
        from_back = u[:, :m] < 0.5
        lane = np.minimum((u[:, m:] * cfg.width).astype(np.int64), cfg.width - 1)
        adv = np.s_[:, cfg.n_agents :]
        self.x[adv] = np.where(out, np.where(from_back, 0, cfg.length - 1), self.x[adv])
        self.y[adv] = np.where(out, lane, self.y[adv])
        self.heading[adv] = np.where(out, 0, self.heading[adv])
        self.speed[adv] = np.where(out, np.where(from_back, cfg.adversary_top, 0), self.speed[adv])

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
            hit = (cell[:, :, None] == cell[:, None, :]) | (mid[:, :, None] == mid[:, None, :])
            crashed |= (hit & self._counted_pair).any(axis=2)
            x, y = nx, ny
        self.x, self.y = x, y
        return crashed, bounced

    # ------------------------------------------------------------ observation
    def offsets(self, envs: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Offsets in cells ``[E, N, C]`` from each agent to every car (its own car included, at 0)."""
        n = self.cfg.n_agents
        x, y = self.x[envs], self.y[envs]
        return x[:, None, :] - x[:, :n, None], y[:, None, :] - y[:, :n, None]

    def visible(self, rel_x: np.ndarray, rel_y: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Which cars at offsets ``[..., N, C]`` an agent with ``heading [..., N]`` senses: within ``sensor_range``
        and inside its field of view (``sensor_fov`` degrees, centred on the heading)."""
        cfg = self.cfg
        ok = rel_x * rel_x + rel_y * rel_y <= cfg.sensor_range**2
        if cfg.sensor_fov < 360:
            along = rel_x * DX[heading][..., None] + rel_y * DY[heading][..., None]
            norm = np.sqrt((rel_x * rel_x + rel_y * rel_y) * (DX[heading] ** 2 + DY[heading] ** 2)[..., None])
            ok &= along >= np.cos(np.radians(cfg.sensor_fov / 2)) * norm - 1e-9
        return ok

    def sees(self, rel_x: np.ndarray, rel_y: np.ndarray, heading: np.ndarray, dist: np.ndarray) -> np.ndarray:
        """``visible`` less, with ``adversary_stealth``, each adversary for the agent it chases (its closest agent:
        ``dist [E, N, C]``, the agents' distances to every car)."""
        ok = self.visible(rel_x, rel_y, heading)
        if self.cfg.adversary_stealth and self.cfg.n_adversaries:
            n = self.cfg.n_agents
            target = np.argmin(dist[:, :, n:], axis=1)  # [E, M] the agent each adversary chases
            ok[:, :, n:] &= target[:, None, :] != np.arange(n)[None, :, None]
        return ok

    def nearest(self, envs: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the ``observe_k`` cars each agent observes ``[E, N, k]``, their distances — inf for an empty slot —, and
        each agent's distance to its closest car, seen or not ``[E, N]``)."""
        cfg = self.cfg
        n, k = cfg.n_agents, cfg.observe_k
        rel_x, rel_y = self.offsets(envs)
        dist = np.sqrt((rel_x * rel_x + rel_y * rel_y).astype(np.float64)) + self._self_mask
        closest = dist.min(axis=2)
        dist = np.where(self.sees(rel_x, rel_y, self.heading[envs][:, :n], dist), dist, np.inf)
        near = np.argmin(dist, axis=2)[..., None] if k == 1 else np.argsort(dist, axis=2, kind="stable")[..., :k]
        return near, np.take_along_axis(dist, near, axis=2), closest

    def team_observed(self, near: np.ndarray, near_dist: np.ndarray) -> np.ndarray:
        """``[E, C]``: which cars some agent observes (what the team as a whole could tell each other)."""
        return ((near[..., None] == np.arange(self.cfg.n_cars)) & np.isfinite(near_dist)[..., None]).any(axis=(1, 2))

    def _observe(self, envs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observations ``[len(envs), N, D]`` and each agent's distance to its closest car."""
        cfg = self.cfg
        n = cfg.n_agents
        x, y, h, v = self.x[envs], self.y[envs], self.heading[envs], self.speed[envs]
        rel_x, rel_y = self.offsets(envs)
        near, near_dist, closest = self.nearest(envs)

        w1, l1 = float(cfg.width - 1), float(cfg.length - 1)
        own_y = y[:, :n].astype(np.float32)
        own = [
            (2.0 * own_y / w1 - 1.0)[..., None],
            _ONE_HOT[h[:, :n]],
            (v[:, :n] / cfg.max_speed).astype(np.float32)[..., None],
            (own_y / w1)[..., None],
            ((w1 - own_y) / w1)[..., None],
            (2.0 * x[:, :n] / l1 - 1.0).astype(np.float32)[..., None],
        ]
        seen = np.isfinite(near_dist).astype(np.float32)[..., None]  # [E, N, k, 1]
        nh = np.take_along_axis(h[:, None, :].repeat(n, axis=1), near, axis=2)
        nv = np.take_along_axis(v[:, None, :].repeat(n, axis=1), near, axis=2)
        r = np.float32(cfg.sensor_range)
        neighbour = seen * np.concatenate(
            [
                np.ones_like(seen),
                (np.take_along_axis(rel_x, near, axis=2) / r).astype(np.float32)[..., None],
                (np.take_along_axis(rel_y, near, axis=2) / r).astype(np.float32)[..., None],
                _ONE_HOT[nh],
                (nv / cfg.top_speed).astype(np.float32)[..., None],
            ],
            axis=3,
        )
        parts = [*own, neighbour.reshape(len(envs), n, -1)]
        if cfg.team_observations:  # each teammate's private observation, teammates in index order
            private = np.concatenate(parts, axis=2)
            parts.append(private[:, self._others[:, : n - 1]].reshape(len(envs), n, -1))
        if cfg.full_information:
            me, o = np.arange(n)[:, None], self._others  # [N, 1], [N, C−1]
            speed = v[:, o] / cfg.top_speed  # [E, N, C−1]
            adversary = np.broadcast_to(o >= n, speed.shape)
            full = np.stack([rel_x[:, me, o] / l1, rel_y[:, me, o] / w1, speed, adversary], axis=3, dtype=np.float32)
            parts.append(full.reshape(len(envs), n, -1))
        if cfg.team_sightings:
            parts.append(self._team_sightings(self.team_observed(near, near_dist), rel_x, rel_y, v, h))
        obs = np.concatenate(parts, axis=2)
        np.clip(obs, -1.0, 1.0, out=obs)
        if cfg.team_words:  # bits, nothing to clip
            obs = np.concatenate([obs, self._team_words(obs)], axis=2)
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
