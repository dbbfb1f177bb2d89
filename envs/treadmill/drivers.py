"""A family of reactive drivers, and what each of them is told: its own sensor, its teammates' sensors, or a 16-bit
message per teammate.

One controller (``family_actions``) with a few parameters (``DriverParams``): how close a car must be to be fled
(``danger``; ``danger_adversary`` for a car known to be an adversary), how a car with nothing to flee holds its place
on the window (``hold``: drive straight at the belt's speed, circle, or weave), how fast it flees (``flee_pace``), and
whether it brakes for a car ahead instead of swerving (``brake``). Only what the threat list contains differs:

* ``private`` — the cars the agent's own sensor reports (its observation: no ally/adversary flag);
* ``team`` — also every car a teammate observes and every teammate's own position (what lossless messages carrying
  each teammate's observation could tell): a car some agent observes that is not at a teammate's position is an
  adversary;
* ``team16`` — also what a fixed, hand-written 16-bit code per teammate carries (``encode16``): a seen flag and the
  window cell (7 + 7 bits) of the car the teammate observes that closes in fastest on another car it observes or on
  itself (a chaser, most of the time: the code cannot tell an ally from an adversary either). The listener drops a
  reported car in its own cell and treats the others like cars it senses.

All three read only what they are told (``private`` only the observation); ``team`` and ``team16`` get their
teammates' observations from the engine as a stand-in for the channel.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from convoy.envs.treadmill.config import N_HEADINGS, NEIGHBOUR_FEATURES, OWN_FEATURES, TreadmillConfig
from convoy.envs.treadmill.engine import DX, DY
from convoy.envs.treadmill.scripted import heading_towards, own_state, steer_action

HOLDS = ("straight", "circle", "weave")


@dataclass(frozen=True)
class DriverParams:
    """One member of the family (see the module docstring)."""

    danger: float = 12.0  # cells: flee a sensed car (ally or adversary, unknown) closer than this
    danger_adversary: float = 20.0  # cells: flee a car known to be an adversary closer than this (team drivers)
    hold: str = "straight"  # straight | circle | weave: what a car with nothing to flee does
    flee_pace: int = 3  # window speed (cells per step) when fleeing, before the belt is added
    brake: bool = False  # a threat ahead (in front of the car): brake to 0 and steer aside rather than flee
    band: float = 10.0  # cells behind the middle of the window within which circling / weaving holds the place

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
    mid_x, mid_y = (cfg.length - 1) / 2.0, (cfg.width - 1) / 2.0
    dist = np.maximum(np.hypot(threat_dx, threat_dy), 1e-6)
    flee_x, flee_y = -threat_dx / dist, -threat_dy / dist
    home_x = np.clip((mid_x - x) / (cfg.length / 4.0), -1.0, 1.0)
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
        calm = ~threat & (np.abs(wall_x) + np.abs(wall_y) == 0) & (x > mid_x - p.band)
        if p.hold == "circle":  # full circles at top speed: the car drifts back with the belt, then drives up again
            held = 3 * 2 + np.where(speed < cfg.max_speed, 2, 1)
        else:  # weave: ±45° around the road's direction, four steps each way, at top speed
            left = (t // 4) % 2 == 0
            want_h = np.where(left, 1, N_HEADINGS - 1)
            held = steer_action(heading, speed, np.full_like(heading, want_h), np.full_like(speed, cfg.max_speed))
        act = np.where(calm, held, act)
    return act


def slot_cars(obs: np.ndarray, cfg: TreadmillConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cars an agent's sensor reports: (seen ``[B, N, k]``, dx, dy) in cells, from observations ``[B, N, D]``."""
    k = cfg.observe_k
    slots = obs[..., OWN_FEATURES : OWN_FEATURES + k * NEIGHBOUR_FEATURES].reshape(*obs.shape[:-1], k, -1)
    return slots[..., 0] > 0.5, slots[..., 1] * cfg.sensor_range, slots[..., 2] * cfg.sensor_range


def closest_threat(dx, dy, flee_mask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of candidate cars ``[B, N, K]``, the closest one to be fled: (dx, dy, any) ``[B, N]``."""
    d = np.where(flee_mask, np.hypot(dx, dy), np.inf)
    i = np.argmin(d, axis=-1)[..., None]
    return (
        np.take_along_axis(dx, i, axis=-1)[..., 0],
        np.take_along_axis(dy, i, axis=-1)[..., 0],
        np.isfinite(np.take_along_axis(d, i, axis=-1)[..., 0]),
    )


def private_actions(obs: np.ndarray, cfg: TreadmillConfig, p: DriverParams, t: int) -> np.ndarray:
    """The family on the agent's own observation: flee the closest sensed car within ``danger``."""
    x, y, h, v = own_state(obs, cfg)
    seen, dx, dy = slot_cars(obs, cfg)
    tdx, tdy, threat = closest_threat(dx, dy, seen & (np.hypot(dx, dy) < p.danger))
    return family_actions(cfg, p, t, x, y, h, v, tdx, tdy, threat)


def closing_slot(obs: np.ndarray, cfg: TreadmillConfig) -> np.ndarray:
    """``[B, N]``: the sensor slot of the car that, by its observed heading and speed, closes in fastest on another
    observed car or on the observer itself (the one a hand-written code reports: chasers close in, allies hold)."""
    k = cfg.observe_k
    seen, dx, dy = slot_cars(obs, cfg)
    slots = obs[..., OWN_FEATURES : OWN_FEATURES + k * NEIGHBOUR_FEATURES].reshape(*obs.shape[:-1], k, -1)
    h = np.argmax(slots[..., 3 : 3 + N_HEADINGS], axis=-1)
    v = np.rint(slots[..., 3 + N_HEADINGS] * cfg.max_speed)
    nx, ny = dx + v * DX[h], dy + v * DY[h]  # where each car is headed in one step (observer's frame)
    zero = np.zeros_like(dx[..., :1])
    tx, ty = np.concatenate([dx, zero], axis=-1), np.concatenate([dy, zero], axis=-1)  # the others and the observer
    target_ok = np.concatenate([seen, np.ones_like(seen[..., :1])], axis=-1)[..., None, :] & ~np.eye(
        k, k + 1, dtype=bool
    )
    before = np.hypot(dx[..., :, None] - tx[..., None, :], dy[..., :, None] - ty[..., None, :])
    after = np.hypot(nx[..., :, None] - tx[..., None, :], ny[..., :, None] - ty[..., None, :])
    approach = np.where(target_ok, after - before, np.inf).min(axis=-1)
    return np.argmin(np.where(seen, approach, np.inf), axis=-1)


def encode16(obs: np.ndarray, cfg: TreadmillConfig, slot: np.ndarray | None = None) -> np.ndarray:
    """Each agent's 16-bit message ``[B, N]`` (uint16): bit 15 = it observes a car, bits 7–13 / 0–6 = that car's
    window cell along / across the road, each axis scaled to 0…127. The car is the one in sensor slot ``slot``
    (default: ``closing_slot``, the car closing in fastest on another)."""
    x, y, _, _ = own_state(obs, cfg)
    seen, dx, dy = slot_cars(obs, cfg)
    if slot is None:
        slot = closing_slot(obs, cfg)
    pick = lambda a: np.take_along_axis(a, slot[..., None], axis=-1)[..., 0]  # noqa: E731
    seen, dx, dy = pick(seen), pick(dx), pick(dy)
    cx = np.clip(np.rint((x + dx) * 127.0 / (cfg.length - 1)), 0, 127).astype(np.uint16)
    cy = np.clip(np.rint((y + dy) * 127.0 / (cfg.width - 1)), 0, 127).astype(np.uint16)
    return np.where(seen, (1 << 15) | (cx << 7) | cy, 0).astype(np.uint16)


def decode16(msg: np.ndarray, cfg: TreadmillConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(seen, x, y) window cell of the car each message reports (inverse of ``encode16``)."""
    m = msg.astype(np.int64)
    seen = (m >> 15) & 1 == 1
    cx = ((m >> 7) & 127) * (cfg.length - 1) / 127.0
    cy = (m & 127) * (cfg.width - 1) / 127.0
    return seen, cx, cy


def team16_actions(obs: np.ndarray, cfg: TreadmillConfig, p: DriverParams, t: int, slot=None) -> np.ndarray:
    """The family told, besides its own sensor, each teammate's 16-bit message (``encode16`` of the teammate's
    observation): reported cars not in the listener's own cell are fled like sensed cars (identity unknown)."""
    n = cfg.n_agents
    x, y, h, v = own_state(obs, cfg)
    seen, dx, dy = slot_cars(obs, cfg)
    heard, cx, cy = decode16(encode16(obs, cfg, slot), cfg)  # [B, N]: what each agent says
    others = np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int64).reshape(n, n - 1)
    hx, hy = cx[:, others] - x[..., None], cy[:, others] - y[..., None]  # [B, N, N−1] in the listener's frame
    cell = max((cfg.length - 1) / 127.0, (cfg.width - 1) / 127.0)
    heard = heard[:, others] & (np.hypot(hx, hy) > 1.5 * cell + 0.5)  # not the listener itself
    all_dx, all_dy = np.concatenate([dx, hx], axis=-1), np.concatenate([dy, hy], axis=-1)
    known = np.concatenate([seen, heard], axis=-1)
    tdx, tdy, threat = closest_threat(all_dx, all_dy, known & (np.hypot(all_dx, all_dy) < p.danger))
    return family_actions(cfg, p, t, x, y, h, v, tdx, tdy, threat)


def team_actions(engine, obs: np.ndarray, p: DriverParams, t: int) -> np.ndarray:
    """The family told every teammate's observation: its own sensed cars, every car a teammate observes and every
    teammate's position (so a car some agent observes away from every teammate is an adversary). It flees the
    closest known adversary within ``danger_adversary``, else the closest teammate or sensed car within ``danger``."""
    cfg = engine.cfg
    n = cfg.n_agents
    x, y, h, v = own_state(obs, cfg)
    rel_x, rel_y = engine.offsets()
    dist = np.hypot(rel_x, rel_y)
    near, near_dist, _ = engine.nearest()
    observed = engine.team_observed(near, near_dist)  # [B, C] some agent observes it
    is_adv = np.arange(cfg.n_cars) >= n
    me = np.eye(n, cfg.n_cars, dtype=bool)
    adv_known = (is_adv & observed)[:, None, :] & (dist < p.danger_adversary)
    # teammates' positions are told; a teammate is fled like a sensed car
    ally_close = (~is_adv & ~me)[None] & (dist < p.danger)
    w = np.where(adv_known, dist, np.where(ally_close, dist + 1e6, np.inf))
    i = np.argmin(w, axis=2)[..., None]
    tdx = np.take_along_axis(rel_x, i, axis=2)[..., 0].astype(np.float64)
    tdy = np.take_along_axis(rel_y, i, axis=2)[..., 0].astype(np.float64)
    threat = np.isfinite(np.take_along_axis(w, i, axis=2)[..., 0])
    return family_actions(cfg, p, t, x, y, h, v, tdx, tdy, threat)
