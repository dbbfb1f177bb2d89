"""A hand-written driving policy: the baseline learners must beat and the demo's driver.

It reads only what an agent observes (its own lateral position, heading, speed and the closest
car's relative position), so it is a legitimate decentralised policy. Rule: when the closest car
is within ``danger`` cells, flee from it at full speed, never towards a nearby road edge;
otherwise cruise forward at treadmill speed and drift back towards the middle of the road.
"""

from __future__ import annotations

import numpy as np

from envs.treadmill.config import N_HEADINGS, TreadmillConfig


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


def scripted_actions(obs: np.ndarray, cfg: TreadmillConfig, danger: float = 8.0) -> np.ndarray:
    """Actions ``[B, N]`` for observations ``[B, N, D]`` of the treadmill."""
    w1 = cfg.width - 1
    lateral = (obs[..., 0] + 1.0) / 2.0 * w1  # cells from the right edge
    heading = np.argmax(obs[..., 1 : 1 + N_HEADINGS], axis=-1)
    speed = np.rint(obs[..., 1 + N_HEADINGS] * cfg.max_speed).astype(np.int64)
    near = 12  # first neighbour's features start after the 12 own features
    dx = obs[..., near] * (cfg.length / 2)
    dy = obs[..., near + 1] * w1
    dist = np.hypot(dx, dy)

    margin = 2 * cfg.max_speed + 1
    away_x, away_y = -dx, -dy
    away_y = np.where((away_y > 0) & (lateral > w1 - margin), 0.0, away_y)
    away_y = np.where((away_y < 0) & (lateral < margin), 0.0, away_y)
    away_x = np.where((away_x == 0) & (away_y == 0), 1.0, away_x)
    centre_y = np.clip((w1 / 2 - lateral) / w1, -0.4, 0.4)  # gentle pull to the middle while cruising
    cruise_y = np.where(np.abs(lateral - w1 / 2) > w1 / 4, centre_y, 0.0)

    flee = dist < danger
    want_heading = np.where(flee, heading_towards(away_x, away_y), heading_towards(np.ones_like(dx), cruise_y))
    want_speed = np.where(flee, cfg.max_speed, cfg.treadmill_speed)
    return steer_action(heading, speed, want_heading, want_speed)
