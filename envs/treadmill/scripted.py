"""Hand-written drivers: the baseline learners must beat, and the full-information reference.

All share one controller, ``family_actions``: keep away from a threat, the road's sides and the window's front and
back, otherwise hold a place on the treadmill (straight back to a home row, circling or weaving); ``DriverParams``
picks a member of the family (``envs.treadmill.drivers`` tunes them). The scripted drivers are its plainest member
(flee at top speed within ``DANGER`` cells, drive straight); they differ only in what they know of the threat.

* ``scripted_actions`` reads an agent's own observation: the threat is the closest car its sensor sees, ally or
  adversary (it cannot tell them apart), so it is a legitimate decentralised policy.
* ``full_information_actions`` reads the engine's state: the threat is the closest *adversary* at any range, or an ally
  the agent sees. With ``team_only`` it knows only the adversaries some agent observes: what an agent could do if
  messages told it, decoded, everything its teammates observe.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from convoy.envs.treadmill.config import DY, LONGITUDINAL, N_HEADINGS, OWN_FEATURES, TreadmillConfig

DANGER = 12.0  # cells: flee a threat closer than this


def heading_towards(ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
    """Nearest of the 8 compass headings to the direction (ax, ay)."""
    return np.rint(np.arctan2(ay, ax) / (np.pi / 4)).astype(np.int64) % N_HEADINGS


def steer_action(
    heading: np.ndarray, speed: np.ndarray, want_heading: np.ndarray, want_speed: np.ndarray
) -> np.ndarray:
    """The one action that turns and accelerates towards the wanted heading and speed."""
    diff = (want_heading - heading) % N_HEADINGS
    steer = np.where(diff == 0, 0, np.where(diff <= 4, 1, -1))
    accel = np.sign(want_speed - speed)
    return 3 * (steer + 1) + (accel + 1)


HOLDS = ("straight", "circle", "weave")


@dataclass(frozen=True)
class DriverParams:
    """One member of the family (see the module docstring)."""

    danger: float = 12.0  # cells: flee a sensed car (ally or adversary, unknown) closer than this
    danger_adversary: float = 20.0  # cells: flee a car known to be an adversary closer than this (team drivers)
    hold: str = "straight"  # straight | circle | weave: what a car with nothing to flee does
    flee_pace: int = 3  # window speed (cells per step) when fleeing, before the belt is added
    brake: bool = False  # a threat ahead (in front of the car): brake to 0 and steer aside rather than flee
    band: float = 10.0  # cells behind the home row within which circling / weaving holds the place
    # where along the window the car holds its place: 0 = the back edge, 1 = the front. Learners hold near the back
    # (~0.3), where a car has the room to outrun a chaser forwards; the middle is the scripted drivers' home
    home: float = 0.5

    def label(self) -> str:
        return ",".join(f"{k}={v}" for k, v in asdict(self).items())


def family_actions(
    cfg: TreadmillConfig,
    p: DriverParams,
    t: int,
    x: np.ndarray,
    y: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    threat_dx: np.ndarray,
    threat_dy: np.ndarray,
    threat: np.ndarray,
) -> np.ndarray:
    """Actions ``[B, N]`` for cars at window cells (x, y) with one threat each at offset (dx, dy) where ``threat``."""
    belt = 0.5 * (cfg.treadmill_speed + (cfg.treadmill_speed_max or cfg.treadmill_speed))  # expected belt
    margin = 4.0 * cfg.max_speed + 2.0
    row_x, mid_y = p.home * (cfg.length - 1), (cfg.width - 1) / 2.0  # the home row; the road's middle
    dist = np.maximum(np.hypot(threat_dx, threat_dy), 1e-6)
    flee_x, flee_y = -threat_dx / dist, -threat_dy / dist
    home_x = np.clip((row_x - x) / (cfg.length / 4.0), -1.0, 1.0)
    home_y = np.clip((mid_y - y) / (cfg.width / 4.0), -1.0, 1.0)
    wall_x = np.clip((margin - x) / margin, 0.0, 1.0) - np.clip((x - (cfg.length - 1 - margin)) / margin, 0.0, 1.0)
    wall_y = np.clip((margin - y) / margin, 0.0, 1.0) - np.clip((y - (cfg.width - 1 - margin)) / margin, 0.0, 1.0)
    ahead = threat & (threat_dx > 0) & (np.abs(threat_dy) < threat_dx) if p.brake else np.zeros_like(threat)
    # braking for a car ahead: fall back on the window and step aside, away from it
    flee_x = np.where(ahead, -1.0, flee_x)
    flee_y = np.where(ahead, np.where(threat_dy > 0, -1.0, 1.0), flee_y)
    want_x = np.where(threat, 2.0 * flee_x, 0.5 * home_x) + 3.0 * wall_x
    want_y = np.where(threat, 2.0 * flee_y, 0.5 * home_y) + 3.0 * wall_y
    pace = np.where(threat, float(p.flee_pace), 1.0)
    norm = np.maximum(np.hypot(want_x, want_y), 1e-6)
    road_x = pace * want_x / norm + belt
    road_y = pace * want_y / norm
    want_speed = np.clip(np.rint(np.hypot(road_x, road_y)), 0, cfg.max_speed).astype(np.int64)
    want_heading = np.where(want_speed > 0, heading_towards(road_x, road_y), heading)
    dy_now = DY[heading]
    side_gap = np.where(dy_now > 0, cfg.width - 1 - y, np.where(dy_now < 0, y, np.inf))
    want_speed = np.where(side_gap < 3 * want_speed + 2, np.minimum(want_speed, 1), want_speed)
    act = steer_action(heading, speed, want_heading, want_speed)
    if p.hold != "straight":
        calm = ~threat & (np.abs(wall_x) + np.abs(wall_y) == 0) & (x > row_x - p.band)
        if p.hold == "circle":  # full circles at top speed: the car drifts back with the belt, then drives up again
            held = 3 * 2 + np.where(speed < cfg.max_speed, 2, 1)
        else:  # weave: ±45° around the road's direction, four steps each way, at top speed
            left = (t // 4) % 2 == 0
            want_h = np.where(left, 1, N_HEADINGS - 1)
            held = steer_action(heading, speed, np.full_like(heading, want_h), np.full_like(speed, cfg.max_speed))
        act = np.where(calm, held, act)
    return act


def own_state(obs: np.ndarray, cfg: TreadmillConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, heading, speed) of each agent, read back from its observation ``[..., D]``."""
    y = (obs[..., 0] + 1.0) / 2.0 * (cfg.width - 1)
    x = (obs[..., LONGITUDINAL] + 1.0) / 2.0 * (cfg.length - 1)
    heading = np.argmax(obs[..., 1 : 1 + N_HEADINGS], axis=-1)
    speed = np.rint(obs[..., 1 + N_HEADINGS] * cfg.max_speed).astype(np.int64)
    return x, y, heading, speed


def scripted_params(cfg: TreadmillConfig, danger: float = DANGER) -> DriverParams:
    """The scripted drivers' member of the family: flee at top speed, else drive straight back to the middle."""
    return DriverParams(danger=danger, flee_pace=cfg.max_speed)


def scripted_actions(obs: np.ndarray, cfg: TreadmillConfig, danger: float = DANGER) -> np.ndarray:
    """Actions ``[B, N]`` from private observations ``[B, N, D]``: flee the closest car the sensor sees."""
    x, y, heading, speed = own_state(obs, cfg)
    seen = obs[..., OWN_FEATURES] > 0.5
    dx = obs[..., OWN_FEATURES + 1] * cfg.sensor_range
    dy = obs[..., OWN_FEATURES + 2] * cfg.sensor_range
    threat = seen & (np.hypot(dx, dy) < danger)
    return family_actions(cfg, scripted_params(cfg, danger), 0, x, y, heading, speed, dx, dy, threat)


def full_information_actions(engine, danger: float = DANGER, team_only: bool = False) -> np.ndarray:
    """Actions ``[B, N]`` from the engine's state: flee the closest adversary, or an ally within sight and ``danger``.

    ``engine`` is a ``TreadmillEngine``. The full-information driver knows every adversary at any range; with
    ``team_only`` it knows only the adversaries that some agent observes (in its ``observe_k`` slots: what perfectly
    decoded messages could tell — the ``team_sightings`` observation).
    Either way it knows who is an adversary, which no observation says.
    """
    cfg = engine.cfg
    n = cfg.n_agents
    rel_x, rel_y = engine.offsets()
    dist = np.hypot(rel_x, rel_y)
    own_sight = engine.visible(rel_x, rel_y, engine.heading[:, :n]) & ~np.eye(n, cfg.n_cars, dtype=bool)
    is_adv = np.arange(cfg.n_cars) >= n
    known_adv = engine.team_observed(*engine.nearest()[:2])[:, None, :] if team_only else np.ones_like(own_sight)
    weight = np.where((is_adv & known_adv) | (~is_adv & own_sight), dist, np.inf)
    near = np.argmin(weight, axis=2)[..., None]
    near_w = np.take_along_axis(weight, near, axis=2)[..., 0]
    dx = np.take_along_axis(rel_x, near, axis=2)[..., 0]
    dy = np.take_along_axis(rel_y, near, axis=2)[..., 0]
    own = np.s_[:, :n]
    x, y, heading, speed = engine.x[own], engine.y[own], engine.heading[own], engine.speed[own]
    return family_actions(cfg, scripted_params(cfg, danger), 0, x, y, heading, speed, dx, dy, near_w < danger)
