"""Every rule of the treadmill highway as a named, documented, validated parameter.

The paper (section 5.1) fixes only the outline: a [100, 100] treadmill that always runs, ≥ 2
cooperative cars and ≥ 1 adversary, the closest car as observation, 8 headings × 3 speed changes,
a distance reward and a crash penalty. Everything else is decided here; see
``docs/treadmill.md`` for the reasoning behind each default.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from envs.config import ConfigError


class TreadmillConfig(BaseModel):
    """Parameters of the treadmill highway. Defaults reproduce the paper's setting."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_agents: int = Field(3, ge=1, le=1024, description="Cooperative autonomous cars controlled by the learners.")
    n_adversaries: int = Field(1, ge=0, le=1024, description="Aggressive scripted cars that chase the closest agent.")
    length: int = Field(100, ge=8, le=100_000, description="Cells along the road; the road wraps (a torus).")
    width: int = Field(100, ge=3, le=100_000, description="Cells across the road; leaving it sideways is a crash.")
    max_speed: int = Field(3, ge=1, le=16, description="Top speed in cells per step; speeds are 0..max_speed.")
    treadmill_speed: int = Field(
        1, ge=0, le=16, description="Cells per step the treadmill carries every car backwards (≤ max_speed)."
    )
    initial_speed: int = Field(1, ge=0, le=16, description="Speed of every car at spawn (≤ max_speed).")
    aggression: float = Field(
        0.7, ge=0.0, le=1.0, description="Probability an adversary chases the closest agent; else it acts at random."
    )
    observe_k: int = Field(1, ge=1, le=64, description="Nearest other cars in an agent's observation.")
    reward_distance_cap: float = Field(
        10.0, gt=0.0, le=1e6, description="d_max: the per-step reward is min(d, d_max) / d_max for the closest car."
    )
    crash_penalty: float = Field(10.0, ge=0.0, le=1e6, description="Reward −crash_penalty to a car that crashes.")
    max_steps: int = Field(200, ge=1, le=1_000_000, description="Truncation horizon of an episode, in steps.")
    spawn_gap: int = Field(
        4, ge=1, le=1000, description="Cars spawn on a lattice of this pitch, so no two start closer than this."
    )

    @property
    def n_cars(self) -> int:
        return self.n_agents + self.n_adversaries

    @property
    def spawn_slots(self) -> int:
        """Cells cars can spawn on: one per ``spawn_gap × spawn_gap`` block."""
        return (self.length // self.spawn_gap) * (self.width // self.spawn_gap)

    @property
    def obs_dim(self) -> int:
        return OWN_FEATURES + self.observe_k * NEIGHBOUR_FEATURES

    @model_validator(mode="after")
    def _consistent(self) -> TreadmillConfig:
        if self.n_cars < 2:
            raise ConfigError(
                "n_adversaries",
                "the reward is the distance to the closest other car, so at least 2 cars are needed: "
                "set n_agents + n_adversaries ≥ 2",
            )
        if self.n_cars > self.spawn_slots:
            raise ConfigError(
                "n_agents",
                f"{self.n_cars} cars do not fit the {self.spawn_slots} spawn cells of a {self.length} × {self.width} "
                f"road with spawn_gap {self.spawn_gap}: allowed range 2 ≤ n_agents + n_adversaries ≤ "
                f"{self.spawn_slots}; use fewer cars, a bigger road or a smaller spawn_gap",
            )
        for name in ("treadmill_speed", "initial_speed"):
            if getattr(self, name) > self.max_speed:
                raise ConfigError(name, f"must be ≤ max_speed ({self.max_speed}); allowed range 0 ≤ {name} ≤ max_speed")
        if self.observe_k > self.n_cars - 1:
            raise ConfigError(
                "observe_k",
                f"an agent can observe at most the {self.n_cars - 1} other cars; "
                f"allowed range 1 ≤ observe_k ≤ n_agents + n_adversaries − 1",
            )
        if self.spawn_gap > min(self.length, self.width):
            raise ConfigError("spawn_gap", f"must be ≤ min(length, width) = {min(self.length, self.width)}")
        return self


N_HEADINGS = 8
N_ACTIONS = 9  # (steer −45°, 0, +45°) × (decelerate, keep, accelerate)
OWN_FEATURES = 1 + N_HEADINGS + 1 + 2  # lateral position, heading one-hot, speed, distance to both edges
NEIGHBOUR_FEATURES = 2 + N_HEADINGS + 1  # relative position (torus-aware), heading one-hot, speed
