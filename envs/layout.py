"""Observation layouts (``EnvSpec.layout``) of the envs whose observations describe other cars, and the check that
``encoder=entity`` can read an env's.

The treadmill's is written here from its config's feature widths and the engine puts it on its spec;
``tests/test_entity.py`` checks it against the engine's observations, so a change to ``_observe`` that this file misses
fails there.
"""

from __future__ import annotations

from convoy.envs.batched import EntitySlots, EnvSpec, ObsLayout, WordSlots
from convoy.envs.treadmill.config import (
    FULL_FEATURES,
    N_HEADINGS,
    NEIGHBOUR_FEATURES,
    OWN_FEATURES,
    SIGHTING_FEATURES,
    WORD_BITS,
    TreadmillConfig,
)
from convoy.validation import ConfigError


def treadmill_layout(cfg: TreadmillConfig) -> ObsLayout:
    """Own features; ``observe_k`` sensor slots (seen, dx, dy, heading one-hot, speed); then, when on, each
    teammate's raw observation and every other car's road-scaled position (not read as cars) and the told
    sightings (known, dx, dy, speed, adversary, with ``sighting_headings`` a heading one-hot) and the teammates'
    16-bit words (``team_words``), in ``engine._observe``'s order."""
    k, others = cfg.observe_k, cfg.n_cars - 1
    sensor = EntitySlots("sensor", OWN_FEATURES, k, NEIGHBOUR_FEATURES, present=0, dx=1, dy=2, heading=3,
                         speed=3 + N_HEADINGS)  # fmt: skip
    cars, unread = [sensor], []
    col = OWN_FEATURES + k * NEIGHBOUR_FEATURES
    if cfg.team_observations:
        unread.append("team_observations")
        col += (cfg.n_agents - 1) * (OWN_FEATURES + k * NEIGHBOUR_FEATURES)
    if cfg.full_information:
        unread.append("full_information")
        col += others * FULL_FEATURES
    if cfg.team_sightings:
        heading = SIGHTING_FEATURES if cfg.sighting_headings else None
        cars.append(EntitySlots("told", col, others, cfg.sighting_features, present=0, dx=1, dy=2, speed=3,
                                adversary=4, heading=heading))  # fmt: skip
        col += others * cfg.sighting_features
    words = None
    if cfg.team_words:
        words = WordSlots(col, cfg.n_agents - 1, WORD_BITS)
        col += (cfg.n_agents - 1) * WORD_BITS
    if col != cfg.obs_dim:
        raise RuntimeError(f"treadmill layout spans {col} columns, the observation {cfg.obs_dim}: update it")
    return ObsLayout(own=OWN_FEATURES, headings=N_HEADINGS, cars=tuple(cars), unread=tuple(unread), words=words)


def entity_layout(spec: EnvSpec) -> ObsLayout:
    """The env's layout, or a ConfigError saying why ``encoder=entity`` cannot read this env."""
    layout = spec.layout
    if layout is None:
        raise ConfigError(
            "encoder",
            f"entity reads the observation as a set of cars, and env {spec.name!r} does not say where they are "
            "(its EnvSpec has no layout); use encoder=mlp, or give the env's spec an ObsLayout (envs/layout.py)",
        )
    if layout.unread:
        blocks = ", ".join(layout.unread)
        raise ConfigError(
            "encoder",
            f"entity reads the observation as a set of cars, and the env's {blocks} block is not laid out as cars; "
            f"use encoder=mlp, or turn {blocks} off in the env's parameters",
        )
    if layout.width > spec.obs_dim:
        raise ValueError(f"{spec.name}: its layout spans {layout.width} columns, the observation {spec.obs_dim}")
    return layout
