"""Model-predictive drivers: one planner, told four levels of information.

Each step, every agent scores ``P`` short plans (a first action, then a second action held for the rest of the
horizon: 81 plans) by simulating its own motion exactly and predicting the cars it knows of, and plays the first
action of the cheapest plan. No memory: the plan is made anew from what the agent knows at this step. What differs
between the levels is only the list of cars it knows of (``Known``):

* ``private`` — the cars its own sensor reports (no ally/adversary flag);
* ``team`` — also every car a teammate observes and every teammate's position, heading and speed (what
  ``team_observations`` hands a learner): a car some agent observes away from every teammate is an adversary;
* ``team16`` — besides its own sensor, one 16-bit word per teammate (``encode_word``): the teammate's own cell
  (6 + 5 bits) and heading (3 bits) — "I am here", which tells the listener which car it senses is not a teammate —
  or, when the teammate sees a car faster than any agent can drive, that chaser's cell and heading;
* ``full`` — every car, its heading and speed, and who is an adversary.

Prediction. Motion relative to another car does not depend on the belt (it carries every car alike), so cars are
predicted on the road: a known ally keeps its heading and speed; an adversary chases the planning agent, closing in
at ``chase`` cells per step — unless it drives too fast to steer (``adversary_steer_speed``): then it keeps its
heading and speed, as the engine moves it; a car of unknown identity is both, weighted by ``p_adversary``. Only
leaving the window depends on the belt, which is unknown (1 or 2 cells per step): the front edge is judged with the
slow belt, the back edge with the fast one.

Cost of a plan, summed over its horizon with discount ``discount``: ``w_danger`` × (1 − d / ``danger``)² per predicted
car within ``danger`` cells, ``w_crash`` per predicted collision (within 1.5 cells) or predicted exit from the window,
``w_edge`` × (1 − gap / ``edge``)² near an edge, minus the step's reward (the capped distance to the closest known car)
× ``w_reward``; at the horizon's end, ``w_home`` × the distance to the home row (``home`` × length, at the mean belt).
The parameters are tuned per level by ``tune_planner`` on tuning episodes (``benchmarks/treadmill_search.py``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from convoy.envs.treadmill.config import CHARGER_RULES, DX, DY, N_ACTIONS, N_HEADINGS, TreadmillConfig
from convoy.envs.treadmill.drivers import peer_index, sensor_slots, slot_speeds
from convoy.envs.treadmill.engine import ACTION_ACCEL, ACTION_STEER, TreadmillEngine
from convoy.envs.treadmill.scripted import own_state

LEVELS = ("private", "team", "team16", "full")
WORD_BITS = 16
COLLIDE = 1.5  # cells: a predicted distance below this counts as a collision

# the plans: (first action, second action held to the horizon's end)
PLAN_FIRST = np.repeat(np.arange(N_ACTIONS), N_ACTIONS)
PLAN_THEN = np.tile(np.arange(N_ACTIONS), N_ACTIONS)


@dataclass(frozen=True)
class PlannerParams:
    """One member of the planner family (see the module docstring); ``SPACE`` bounds what the tuning searches."""

    horizon: int = 6
    discount: float = 0.913
    danger: float = 23.23
    w_danger: float = 4.641
    w_crash: float = 20.95
    chase: float = 3.5
    p_adversary: float = 0.547
    edge: float = 12.62
    w_edge: float = 3.639
    home: float = 0.355
    w_home: float = 0.058
    w_reward: float = 1.259
    w_blind: float = 0.411
    w_phantom: float = 8.258
    phantom: float = 12.12

    def label(self) -> str:
        """Every parameter as ``name=value`` (floats to 4 significant digits), the form ``from_label`` reads."""
        return ",".join(f"{k}={float(f'{v:.4g}') if isinstance(v, float) else v}" for k, v in asdict(self).items())

    @classmethod
    def from_label(cls, label: str) -> PlannerParams:
        values = dict(item.split("=", 1) for item in label.split(","))
        typed: dict[str, Any] = {
            f.name: int(values[f.name]) if f.type == "int" else float(values[f.name]) for f in fields(cls)
        }
        return cls(**typed)


# Where every level's tuning starts: the defaults, the best point of a first cross-entropy search on the private level
# (6 iterations × 12 candidates × 64 episodes from a point found by hand: chase 4, danger 25, w_blind 1, w_phantom 6).
START = PlannerParams()

# (low, high) of each tuned parameter; the horizon is an integer
SPACE: dict[str, tuple[float, float]] = {
    "horizon": (3, 9),
    "discount": (0.6, 1.0),
    "danger": (4.0, 30.0),
    "w_danger": (0.0, 20.0),
    "w_crash": (1.0, 100.0),
    "chase": (0.5, 5.0),
    "p_adversary": (0.0, 1.0),
    "edge": (2.0, 25.0),
    "w_edge": (0.0, 20.0),
    "home": (0.1, 0.9),
    "w_home": (0.0, 0.5),
    "w_reward": (0.0, 3.0),
    "w_blind": (0.0, 5.0),
    "w_phantom": (0.0, 10.0),
    "phantom": (5.0, 40.0),
}


@dataclass
class Known:
    """The cars an agent knows of, ``[B, N, K]`` each: where (window cells), heading and speed, and the chance it is
    an adversary (0 a known ally, 1 a known adversary); and ``[B, N]`` the chance that an adversary it does not know
    of is about (what the phantoms and the look back weigh): none once it knows of every adversary there is."""

    known: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    adversary: np.ndarray
    unseen: np.ndarray


# ------------------------------------------------------------------------------------------------ what agents know
def sensed(obs: np.ndarray, cfg: TreadmillConfig, p: PlannerParams) -> Known:
    """The cars an agent's own sensor reports (``private``): identity unknown."""
    x, y, _, _ = own_state(obs, cfg)
    slots = sensor_slots(obs, cfg)
    seen = slots[..., 0] > 0.5
    return Known(
        known=seen,
        x=x[..., None] + slots[..., 1] * cfg.sensor_range,
        y=y[..., None] + slots[..., 2] * cfg.sensor_range,
        heading=np.argmax(slots[..., 3 : 3 + N_HEADINGS], axis=-1),
        speed=slot_speeds(slots, cfg),
        adversary=np.where(seen, p.p_adversary, 0.0),
        unseen=np.ones(x.shape),
    )


def engine_cars(engine: TreadmillEngine, known: np.ndarray) -> Known:
    """Every other car of each agent as the engine has it, ``known [B, N, C−1]`` saying which the agent knows of;
    identity known (teams identify every car they know: the ones not at a teammate's position are adversaries)."""
    cfg = engine.cfg
    o = engine._others  # [N, C−1]
    n = cfg.n_agents
    adversary = np.where(known, np.broadcast_to((o >= n).astype(np.float64), known.shape), 0.0)
    return Known(
        known=known,
        x=engine.x[:, o].astype(np.float64),
        y=engine.y[:, o].astype(np.float64),
        heading=engine.heading[:, o],
        speed=engine.speed[:, o].astype(np.float64),
        adversary=adversary,
        unseen=(adversary.sum(axis=-1) < cfg.n_adversaries).astype(np.float64),
    )


def team_known(engine: TreadmillEngine) -> Known:
    """``team``: every teammate, and every car some agent observes (what each teammate's observation tells)."""
    cfg = engine.cfg
    near, near_dist, _ = engine.nearest()
    observed = engine.team_observed(near, near_dist)  # [B, C]
    o = engine._others
    return engine_cars(engine, observed[:, o] | (o < cfg.n_agents)[None])


def full_known(engine: TreadmillEngine) -> Known:
    """``full``: every car."""
    return engine_cars(engine, np.ones((engine.num_envs, *engine._others.shape), bool))


def encode_word(obs: np.ndarray, cfg: TreadmillConfig) -> np.ndarray:
    """Each agent's 16-bit word ``[B, N]`` (uint16): bit 15 = a report; bit 14 = it reports a chaser, else itself;
    bits 8–13 / 3–7 = the reported car's window cell along / across the road, scaled to 0…63 / 0…31; bits 0–2 its
    heading. An agent says where it is ("I am here": a listener that compares the words with the cars it senses can
    tell its teammates from the adversary, which its own sensor cannot) unless it observes a car driving faster than
    an agent can (``adversary_speed`` above ``max_speed``): then it reports the fastest such car, surely a chaser."""
    x, y, heading, _ = own_state(obs, cfg)
    slots = sensor_slots(obs, cfg)
    speed = np.where(slots[..., 0] > 0.5, slot_speeds(slots, cfg), -1.0)
    fastest = np.argmax(speed, axis=-1)[..., None, None]
    chaser = np.take_along_axis(slots, fastest, axis=-2)[..., 0, :]
    sure = np.take_along_axis(speed, fastest[..., 0], axis=-1)[..., 0] > cfg.max_speed
    cx = np.where(sure, x + chaser[..., 1] * cfg.sensor_range, x)
    cy = np.where(sure, y + chaser[..., 2] * cfg.sensor_range, y)
    h = np.where(sure, np.argmax(chaser[..., 3 : 3 + N_HEADINGS], axis=-1), heading).astype(np.uint16)
    wx = np.clip(np.rint(cx * 63.0 / (cfg.length - 1)), 0, 63).astype(np.uint16)
    wy = np.clip(np.rint(cy * 31.0 / (cfg.width - 1)), 0, 31).astype(np.uint16)
    return ((1 << 15) | (sure.astype(np.uint16) << 14) | (wx << 8) | (wy << 3) | h).astype(np.uint16)


def decode_word(word: np.ndarray, cfg: TreadmillConfig) -> tuple[np.ndarray, ...]:
    """(a report, a chaser (else the speaker itself), x, y, heading) of each word (inverse of ``encode_word``, to
    the cell's precision)."""
    w = word.astype(np.int64)
    x = ((w >> 8) & 63) * (cfg.length - 1) / 63.0
    y = ((w >> 3) & 31) * (cfg.width - 1) / 31.0
    return (w >> 15) & 1 == 1, (w >> 14) & 1 == 1, x, y, w & 7


def heard_known(obs: np.ndarray, cfg: TreadmillConfig, p: PlannerParams) -> Known:
    """``team16``: the agent's own sensor plus each teammate's word. A teammate that says where it is is a known ally
    (at the belt's speed), and a sensed car at its cell is that ally; a reported chaser is an adversary at top
    speed, and the sensed car at its cell is it. Once every teammate is placed, or the one adversary is reported,
    every car is identified; until then a sensed car the words do not name is an adversary with chance
    ``p_adversary``."""
    n = cfg.n_agents
    own = sensed(obs, cfg, p)
    seen, sure, rx, ry, rh = (a[:, peer_index(n)] for a in decode_word(encode_word(obs, cfg), cfg))  # [B, N, N−1]
    tol = 1.0 + max((cfg.length - 1) / 63.0, (cfg.width - 1) / 31.0)
    near = np.hypot(rx[..., None, :] - own.x[..., :, None], ry[..., None, :] - own.y[..., :, None]) <= tol
    near &= own.known[..., :, None] & seen[..., None, :]  # [B, N, k, N−1]: sensed car k is what word j reports
    is_ally = (near & ~sure[..., None, :]).any(axis=-1)
    is_chaser = (near & sure[..., None, :]).any(axis=-1)
    placed = (seen & ~sure).all(axis=-1, keepdims=True)  # every teammate said where it is
    lone = (seen & sure).any(axis=-1, keepdims=True) & (cfg.n_adversaries == 1)
    sensed_p = np.where(placed | lone, 1.0 - lone, p.p_adversary)  # identified: the unnamed are adversaries/allies
    sensed_p = np.where(is_ally, 0.0, np.where(is_chaser, 1.0, sensed_p))
    new = seen & ~(near.any(axis=-2))  # reported cars the agent does not sense
    known_adv = (own.known * (sensed_p > 0.5)).sum(axis=-1) + (new & sure).sum(axis=-1)
    belt = float(cfg.treadmill_speed_max or cfg.treadmill_speed)
    return Known(
        known=np.concatenate([own.known, new], axis=-1),
        x=np.concatenate([own.x, rx], axis=-1),
        y=np.concatenate([own.y, ry], axis=-1),
        heading=np.concatenate([own.heading, rh], axis=-1),
        speed=np.concatenate([own.speed, np.where(sure, float(cfg.adversary_top), belt)], axis=-1),
        adversary=np.concatenate([np.where(own.known, sensed_p, 0.0), np.where(new & sure, 1.0, 0.0)], axis=-1),
        unseen=np.where((placed[..., 0] | lone[..., 0]) & (known_adv >= cfg.n_adversaries), 0.0, 1.0),
    )


# ------------------------------------------------------------------------------------------------------ the planner
def plan_actions(cfg: TreadmillConfig, p: PlannerParams, x, y, heading, speed, cars: Known) -> np.ndarray:
    """Actions ``[B, N]``: the first action of each agent's cheapest plan, given the cars it knows of."""
    lead = x.shape
    m = int(np.prod(lead))
    hz = int(p.horizon)
    # own motion on the road (no belt), [M, P] per step
    h = np.broadcast_to(heading.reshape(m, 1), (m, len(PLAN_FIRST))).astype(np.int64)
    v = np.broadcast_to(speed.reshape(m, 1), h.shape).astype(np.int64)
    px = np.broadcast_to(x.reshape(m, 1), h.shape).astype(np.float64)
    py = np.broadcast_to(y.reshape(m, 1), h.shape).astype(np.float64)
    kx, ky = cars.x.reshape(m, 1, -1).astype(np.float64), cars.y.reshape(m, 1, -1).astype(np.float64)  # [M, 1, K]
    known = cars.known.reshape(m, 1, -1)
    adv = cars.adversary.reshape(m, 1, -1)
    cdx, cdy = DX[cars.heading].reshape(m, 1, -1), DY[cars.heading].reshape(m, 1, -1)
    cv = cars.speed.reshape(m, 1, -1)
    ax = np.broadcast_to(kx, (m, len(PLAN_FIRST), kx.shape[-1]))
    ay = np.broadcast_to(ky, ax.shape)
    unseen = cars.unseen.reshape(m, 1)
    # a car too fast to steer (``adversary_steer_speed``) drives on in a line, whoever it chases
    charging = cv > cfg.adversary_steer_cap  # [M, 1, K]
    # phantoms: a possible chaser in each compass direction the agent's sensor cannot see now, ``phantom`` cells away
    blind = np.flatnonzero(~_sees(cfg, np.zeros(1, np.int64), np.arange(N_HEADINGS)))  # offsets from the heading
    ph = (heading.reshape(m, 1) + blind[None, :]) % N_HEADINGS  # [M, F]
    fx = np.broadcast_to((x.reshape(m, 1) + p.phantom * _UX[ph])[:, None, :], (m, len(PLAN_FIRST), len(blind)))
    fy = np.broadcast_to((y.reshape(m, 1) + p.phantom * _UY[ph])[:, None, :], fx.shape)
    cost = np.zeros(h.shape)
    weight = 1.0
    belt_lo = cfg.treadmill_speed
    belt_hi = cfg.treadmill_speed_max or cfg.treadmill_speed
    cap = cfg.reward_distance_cap
    near = lambda d: np.clip(1.0 - d / p.danger, 0.0, None) ** 2  # noqa: E731
    for t in range(1, hz + 1):
        act = PLAN_FIRST if t == 1 else PLAN_THEN
        h = (h + ACTION_STEER[act]) % N_HEADINGS
        v = np.clip(v + ACTION_ACCEL[act], 0, cfg.max_speed)
        px = px + v * DX[h]
        py = py + v * DY[h]
        # allies keep heading and speed; adversaries close in on where the agent will be, chargers drive on
        bx, by = kx + t * cv * cdx, ky + t * cv * cdy  # [M, 1, K]
        ax, ay, d_adv = _close_in(ax, ay, px, py, p.chase)  # [M, P, K]
        d_ally = np.hypot(px[..., None] - bx, py[..., None] - by)
        if charging.any():
            ax, ay = np.where(charging, bx, ax), np.where(charging, by, ay)
            d_adv = np.where(charging, d_ally, d_adv)
        danger = adv * (p.w_danger * near(d_adv) + p.w_crash * (d_adv < COLLIDE))
        danger += (1.0 - adv) * (p.w_danger * near(d_ally) + p.w_crash * (d_ally < COLLIDE))
        closest = np.where(known, adv * d_adv + (1 - adv) * d_ally, np.inf).min(axis=-1)
        reward = np.minimum(closest, cap) / cap
        # the window: the front judged on the slow belt, the back on the fast one
        front, back = cfg.length - 1 - (px - t * belt_lo), px - t * belt_hi
        side = np.minimum(py, cfg.width - 1 - py)
        gap_edge = np.minimum(np.minimum(front, back), side)
        out = gap_edge < 0
        edge = p.w_edge * np.clip(1.0 - gap_edge / p.edge, 0.0, None) ** 2 + p.w_crash * out
        if p.w_phantom and len(blind):
            fx, fy, d_ph = _close_in(fx, fy, px, py, p.chase)
            edge = edge + unseen * p.w_phantom * near(d_ph).sum(axis=-1) / N_HEADINGS
        # looking back: the chaser comes from behind, into the sensor's blind spot
        edge = edge + unseen * p.w_blind * ~_sees(cfg, h, np.full_like(h, 4))
        cost += weight * (np.where(known, danger, 0.0).sum(axis=-1) + edge - p.w_reward * reward)
        weight *= p.discount
    home_x = p.home * (cfg.length - 1) + hz * 0.5 * (belt_lo + belt_hi)
    cost += p.w_home * np.abs(px - home_x)
    best = np.argmin(cost, axis=-1)
    return PLAN_FIRST[best].reshape(lead)


def _close_in(cx, cy, px, py, chase: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Chasers at ``(cx, cy)`` ``[M, P, K]`` after moving ``chase`` cells straight at the agent's planned place
    ``(px, py)`` ``[M, P]`` (never past it): their new places and their distance from it."""
    gx, gy = px[..., None] - cx, py[..., None] - cy
    gap = np.maximum(np.hypot(gx, gy), 1e-9)
    step = np.minimum(chase, gap) / gap
    cx, cy = cx + gx * step, cy + gy * step
    return cx, cy, np.hypot(px[..., None] - cx, py[..., None] - cy)


_UX = DX / np.hypot(DX, DY)
_UY = DY / np.hypot(DX, DY)


def _sees(cfg: TreadmillConfig, heading: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Whether a car facing ``heading`` has compass ``direction`` inside its field of view (broadcast)."""
    diff = np.abs(((direction - heading) % N_HEADINGS + 4) % N_HEADINGS - 4) * 45.0
    return diff <= cfg.sensor_fov / 2 + 1e-9


def level_actions(level: str, engine: TreadmillEngine, obs: np.ndarray, p: PlannerParams) -> np.ndarray:
    """The planner told information level ``level`` (``LEVELS``) driving ``engine``'s agents from ``obs``."""
    cfg = engine.cfg
    x, y, heading, speed = own_state(obs, cfg)
    if level == "private":
        cars = sensed(obs, cfg, p)
    elif level == "team":
        cars = team_known(engine)
    elif level == "team16":
        cars = heard_known(obs, cfg, p)
    elif level == "full":
        cars = full_known(engine)
    else:
        raise ValueError(f"unknown information level {level!r}; choose one of: {', '.join(LEVELS)}")
    return plan_actions(cfg, p, x, y, heading, speed, cars)


def planner_returns(cfg: TreadmillConfig, level: str, p: PlannerParams, episodes: int, seed: int) -> np.ndarray:
    """Per-episode return (mean over agents) of the planner at ``level`` on ``episodes`` episodes seeded ``seed``."""
    from convoy.envs.rollout import rollout

    engine = TreadmillEngine(cfg, episodes, autoreset=False)
    return rollout(engine, lambda obs: level_actions(level, engine, obs, p), seed=seed).mean_return


def from_vector(u: np.ndarray) -> PlannerParams:
    """Parameters from a point of the unit cube over ``SPACE`` (the tuning's search space)."""
    values: dict[str, Any] = {}
    for ui, (name, (lo, hi)) in zip(np.clip(u, 0.0, 1.0), SPACE.items(), strict=True):
        v = lo + ui * (hi - lo)
        values[name] = round(v) if name == "horizon" else float(f"{v:.4g}")  # what ``label`` writes, exactly
    return PlannerParams(**values)


def to_vector(p: PlannerParams) -> np.ndarray:
    return np.array([(getattr(p, k) - lo) / (hi - lo) for k, (lo, hi) in SPACE.items()])


def tune_planner(
    cfg: TreadmillConfig,
    level: str,
    start: PlannerParams | None = None,
    iterations: int = 6,
    population: int = 16,
    elite: int = 4,
    episodes: int = 64,
    seed: int = 1,
    rng_seed: int = 0,
    spread: float = 0.15,
    log=None,
) -> tuple[PlannerParams, float]:
    """Cross-entropy search over ``SPACE`` on ``episodes`` tuning episodes (seed ``seed``): a Gaussian in the unit
    cube, started at ``start``, refit to the ``elite`` best of each ``population``. Every candidate plays the same
    episodes. Returns (the best parameters seen, their tuning mean)."""
    rng = np.random.default_rng(rng_seed)
    mean = to_vector(start or PlannerParams())
    std = np.full_like(mean, spread)
    best, best_val = start or PlannerParams(), -np.inf
    for it in range(iterations):
        noise = rng.standard_normal((population - 1, len(mean)))
        cand = [from_vector(mean)] + [from_vector(mean + std * z) for z in noise]
        vals = np.array([planner_returns(cfg, level, c, episodes, seed).mean() for c in cand])
        order = np.argsort(-vals, kind="stable")
        if vals[order[0]] > best_val:
            best, best_val = cand[order[0]], float(vals[order[0]])
        top = np.stack([to_vector(cand[i]) for i in order[:elite]])
        mean, std = top.mean(axis=0), np.maximum(0.7 * top.std(axis=0) + 0.3 * std, 0.02)
        if log is not None:
            elite_mean = vals[order[:elite]].mean()
            log(f"{level} iteration {it + 1}/{iterations}: best {vals[order[0]]:.1f}, elite mean {elite_mean:.1f}")
    return best, best_val


# Each level's parameters, chosen by ``benchmarks/treadmill_search.py`` (docs/figures/treadmill_search.json's
# "planners"; a test keeps the two equal).
TUNED: dict[str, PlannerParams] = {
    "private": PlannerParams.from_label(
        "horizon=6,discount=0.8869,danger=22.96,w_danger=4.431,w_crash=27.93,chase=4.388,p_adversary=0.3581,edge=13.52,w_edge=0.4404,home=0.2588,w_home=0.01923,w_reward=1.193,w_blind=0.2518,w_phantom=7.939,phantom=8.314"
    ),
    "team": PlannerParams.from_label(
        "horizon=5,discount=0.8499,danger=20.13,w_danger=5.895,w_crash=20.76,chase=3.557,p_adversary=0.5336,edge=15.61,w_edge=5.137,home=0.3996,w_home=0.02688,w_reward=1.095,w_blind=0.006734,w_phantom=6.542,phantom=11.18"
    ),
    "team16": PlannerParams.from_label(
        "horizon=5,discount=0.9129,danger=22.47,w_danger=3.057,w_crash=26.93,chase=2.92,p_adversary=0.5649,edge=11.34,w_edge=1.93,home=0.5232,w_home=0.0341,w_reward=0.8687,w_blind=0.0193,w_phantom=7.82,phantom=8.732"
    ),
    "full": PlannerParams.from_label(
        "horizon=6,discount=0.9103,danger=18.01,w_danger=7.677,w_crash=5.774,chase=3.462,p_adversary=0.4923,edge=12.49,w_edge=6.146,home=0.4222,w_home=0.07518,w_reward=1.9,w_blind=0.05371,w_phantom=5.554,phantom=16.15"
    ),
}

# Each level tuned on the charger rules (``CHARGER_RULES``; docs/figures/treadmill_charger.json's "planners").
CHARGER_TUNED: dict[str, PlannerParams] = {
    "private": PlannerParams.from_label(
        "horizon=5,discount=0.8373,danger=24.02,w_danger=5.255,w_crash=29.44,chase=3.709,p_adversary=0.5475,edge=14.64,w_edge=5.352,home=0.3175,w_home=0.05556,w_reward=1.03,w_blind=0.0,w_phantom=7.704,phantom=7.025"
    ),
    "team": PlannerParams.from_label(
        "horizon=6,discount=0.8578,danger=23.7,w_danger=4.247,w_crash=28.52,chase=3.105,p_adversary=0.6403,edge=14.67,w_edge=4.12,home=0.4646,w_home=0.03177,w_reward=1.261,w_blind=0.1459,w_phantom=7.968,phantom=17.19"
    ),
    "team16": PlannerParams.from_label(
        "horizon=6,discount=0.9565,danger=23.88,w_danger=3.306,w_crash=18.31,chase=3.222,p_adversary=0.4041,edge=15.37,w_edge=3.27,home=0.5086,w_home=0.0,w_reward=0.4791,w_blind=0.0,w_phantom=9.476,phantom=11.32"
    ),
    "full": PlannerParams.from_label(
        "horizon=5,discount=0.8803,danger=22.0,w_danger=5.876,w_crash=36.43,chase=3.413,p_adversary=0.752,edge=10.33,w_edge=4.694,home=0.4634,w_home=0.06505,w_reward=0.9244,w_blind=0.0,w_phantom=7.571,phantom=13.28"
    ),
}


def tuned_for(cfg: TreadmillConfig) -> dict[str, PlannerParams]:
    """Each level's parameters for ``cfg``: those tuned on its rules where a search ran on them (the charger rules),
    else those tuned on the default rules — a reference should be the strongest policy known on the rules it plays."""
    return CHARGER_TUNED if cfg.moves_as(CHARGER_RULES) else TUNED
