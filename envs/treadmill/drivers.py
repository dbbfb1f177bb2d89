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

import numpy as np

from convoy.envs.treadmill.config import DX, DY, N_HEADINGS, NEIGHBOUR_FEATURES, OWN_FEATURES, TreadmillConfig
from convoy.envs.treadmill.scripted import DriverParams, family_actions, own_state


def sensor_slots(obs: np.ndarray, cfg: TreadmillConfig) -> np.ndarray:
    """An agent's ``observe_k`` sensor slots ``[..., k, NEIGHBOUR_FEATURES]`` from its observation ``[..., D]``."""
    k = cfg.observe_k
    return obs[..., OWN_FEATURES : OWN_FEATURES + k * NEIGHBOUR_FEATURES].reshape(*obs.shape[:-1], k, -1)


def slot_speeds(slots: np.ndarray, cfg: TreadmillConfig) -> np.ndarray:
    """Cells per step of the car in each sensor slot ``[..., k]`` (other cars' speeds are scaled by ``top_speed``)."""
    return np.rint(slots[..., 3 + N_HEADINGS] * cfg.top_speed)


def peer_index(n: int) -> np.ndarray:
    """``[N, N−1]``: every agent's teammates in order (agent i's row skips i), to gather what each one hears."""
    return np.array([[j for j in range(n) if j != i] for i in range(n)], dtype=np.int64).reshape(n, n - 1)


def slot_cars(obs: np.ndarray, cfg: TreadmillConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cars an agent's sensor reports: (seen ``[B, N, k]``, dx, dy) in cells, from observations ``[B, N, D]``."""
    slots = sensor_slots(obs, cfg)
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
    slots = sensor_slots(obs, cfg)
    h = np.argmax(slots[..., 3 : 3 + N_HEADINGS], axis=-1)
    v = slot_speeds(slots, cfg)
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
    others = peer_index(n)
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
