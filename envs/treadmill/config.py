"""Every rule of the treadmill highway as a named, documented, validated parameter.

The paper (section 5.1) fixes only the outline: a [100, 100] treadmill that always runs, cars that enter and exit
at its front and back, ≥ 2 cooperative cars and ≥ 1 aggressive adversary, the closest car as observation (no
ally/adversary flag), 3 steering × 3 acceleration actions, a distance reward and a large crash penalty. Everything
else is decided here so that (a) no open-loop policy is competitive, (b) what other cars see is worth reward to an
agent and (c) one crash costs everyone; ``docs/treadmill.md`` has the measurements behind each default.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from convoy.validation import ConfigError

# The kinds of quantity a rule is, with their bounds (a field may narrow them).
Cars = Annotated[int, Field(ge=0, le=1024)]
Cells = Annotated[int, Field(ge=3, le=100_000)]
Speed = Annotated[int, Field(ge=0, le=16)]  # cells per step
Distance = Annotated[float, Field(gt=0.0, le=1e6)]  # cells
Probability = Annotated[float, Field(ge=0.0, le=1.0)]


class TreadmillConfig(BaseModel):
    """Parameters of the treadmill highway."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_agents: int = Field(3, ge=1, le=1024, description="Cooperative autonomous cars controlled by the learners.")
    n_adversaries: Cars = Field(1, description="Aggressive scripted cars that chase the closest agent.")
    length: int = Field(
        100, ge=8, le=100_000, description="Cells along the road: the treadmill's window; leaving it is a crash."
    )
    width: Cells = Field(100, description="Cells across the road; leaving it sideways is a crash.")
    max_speed: int = Field(3, ge=1, le=16, description="Top speed in cells per step; speeds are 0..max_speed.")
    treadmill_speed: Speed = Field(1, description="Cells per step the treadmill carries every car back (≤ max_speed).")
    initial_speed: Speed = Field(1, description="Speed of every car at spawn (≤ max_speed).")
    adversary_speed: Speed | None = Field(
        None,
        description="Top speed of the adversaries if set (≥ 1; default: max_speed). Above max_speed a chaser "
        "cannot be outrun, only dodged as it arrives: that needs to know where it is.",
    )
    adversary_steer_speed: Speed | None = Field(
        None,
        description="If set, an adversary driving faster than this cannot steer (its steering actions keep its "
        "heading): a fast chaser charges in a line and must slow down to turn, so a car that knows it is coming "
        "can step out of its way (default: it steers at any speed).",
    )
    aggression: Probability = Field(
        0.8,
        description="Chance an adversary chases the closest agent, else it acts at random (0.8: what teammates "
        "know pays most; at 0.9 a private driver rarely escapes).",
    )
    sensor_range: Distance = Field(
        60.0,
        description="Cells an agent's sensor reaches; farther cars are unobserved (zeros). 60: a teammate sees the "
        "chaser coming up behind another (at 20 what teammates see is worth nothing to a tuned driver).",
    )
    sensor_fov: float = Field(
        240.0, gt=0.0, le=360.0, description="Sensor's field of view in degrees, around the heading."
    )
    observe_k: int = Field(
        3,
        ge=1,
        le=64,
        description="Nearest other cars (within sensor_range) an agent observes (3, or every other car when there "
        "are fewer: with one slot a teammate's closest car is usually another teammate, not the chaser).",
    )
    full_information: bool = Field(
        False,
        description="Reference only: append every other car's position, speed and an adversary flag to each agent's "
        "observation (more than messages could carry: also the cars no agent observes).",
    )
    team_observations: bool = Field(
        False,
        description="Reference only: append every teammate's own observation to each agent's (what lossless, "
        "unlearned messages could carry: the learner that bounds what MA-MeSN's messages can add).",
    )
    team_sightings: bool = Field(
        False,
        description="Reference only: append, in the agent's own frame, every teammate and every car some agent "
        "observes, with an adversary flag (what perfectly decoded messages could tell).",
    )
    sighting_headings: bool = Field(
        False,
        description="With team_sightings: each told car's heading too (a one-hot, as the agent's own sensor slots "
        "give it). A charger too fast to steer is dangerous along its heading, and both told planners know it; off "
        "gives the sightings of the results measured before it existed.",
    )
    team_words: bool = Field(
        False,
        description="Reference only: append each teammate's 16-bit word as 16 bits, teammates in index order — the "
        "hand-written code of the team16 driver and planner (envs/treadmill/drivers.py encode16: a seen flag and the "
        "window cell of the car the teammate sees closing in fastest). A learner told these hears the 2-byte "
        "channel a designed protocol fills, instead of learning one.",
    )
    reward_distance_cap: Distance = Field(10.0, description="d_max: the per-step reward is min(d, d_max) / d_max.")
    crash_penalty: float = Field(10.0, ge=0.0, le=1e6, description="Reward −crash_penalty to a car that crashes.")
    max_steps: int = Field(200, ge=1, le=1_000_000, description="Truncation horizon of an episode, in steps.")
    spawn_gap: int = Field(
        4, ge=1, le=1000, description="Agents spawn on a lattice of this pitch: no two start closer."
    )
    spawn_heading_spread: int = Field(
        4,
        ge=0,
        le=4,
        description="Agents spawn facing a heading drawn uniformly from −spread … +spread steps of 45° around "
        "forward (0: all face forward): no fixed action sequence can hold a place for every start, a car that "
        "looks at its heading and place can.",
    )
    adversary_stealth: bool = Field(
        False,
        description="An adversary is invisible to the agent it chases (its closest agent), as a car coming up in "
        "the blind spot: only teammates can see it, so knowledge of the danger sits with others than the one in it.",
    )
    treadmill_speed_max: Speed | None = Field(
        2,
        description="If set (≥ treadmill_speed), the belt's speed varies: each env's belt runs at a speed in "
        "treadmill_speed … treadmill_speed_max, drawn anew with probability treadmill_switch_prob per step (the "
        "traffic speeds up and slows down), so holding a place on the window needs feedback, not a fixed cycle.",
    )
    treadmill_switch_prob: Probability = Field(
        0.03, description="Chance per step that a varying belt (treadmill_speed_max) draws a new speed."
    )

    @classmethod
    def v2(cls, **overrides) -> TreadmillConfig:
        """The second rule set (``V2_RULES``): what every result measured before the current defaults used."""
        return cls(**(V2_RULES | overrides))

    def moves_as(self, rules: dict) -> bool:
        """Whether these rules are the defaults with ``rules`` set, up to what the agents are told
        (``INFORMATION_FIELDS``): a reference tuned on those rules is tuned on these."""
        told = {name: TreadmillConfig.model_fields[name].default for name in INFORMATION_FIELDS}
        return self.model_copy(update=told) == TreadmillConfig(**rules)

    @property
    def adversary_top(self) -> int:
        """The adversaries' top speed."""
        return self.max_speed if self.adversary_speed is None else self.adversary_speed

    @property
    def adversary_steer_cap(self) -> int:
        """The fastest an adversary steers at (``adversary_steer_speed``; unset: any speed it can drive)."""
        return self.top_speed if self.adversary_steer_speed is None else self.adversary_steer_speed

    @property
    def top_speed(self) -> int:
        """The fastest any car may go: the scale of other cars' speeds in an observation."""
        return max(self.max_speed, self.adversary_top)

    @property
    def n_cars(self) -> int:
        return self.n_agents + self.n_adversaries

    @property
    def spawn_blocks(self) -> tuple[int, int, int]:
        """(first block along the road, blocks along, blocks across) of the spawn lattice: the middle half."""
        along = self.length // self.spawn_gap
        first = along // 4
        return first, max(1, along - 2 * first), self.width // self.spawn_gap

    @property
    def spawn_slots(self) -> int:
        """Cells agents can spawn on: one per ``spawn_gap × spawn_gap`` block of the window's middle half."""
        _, along, across = self.spawn_blocks
        return along * across

    @property
    def sighting_features(self) -> int:
        """Columns per told car: known, dx, dy, speed, adversary, then its heading one-hot if ``sighting_headings``."""
        return SIGHTING_FEATURES + (N_HEADINGS if self.sighting_headings else 0)

    @property
    def obs_dim(self) -> int:
        private = OWN_FEATURES + self.observe_k * NEIGHBOUR_FEATURES
        team = (self.n_agents - 1) * private if self.team_observations else 0
        full = (self.n_cars - 1) * FULL_FEATURES if self.full_information else 0
        sightings = (self.n_cars - 1) * self.sighting_features if self.team_sightings else 0
        words = (self.n_agents - 1) * WORD_BITS if self.team_words else 0
        return private + team + full + sightings + words

    @model_validator(mode="before")
    @classmethod
    def _fitted_defaults(cls, data: Any) -> Any:
        """Defaults that must fit other fields, unless given: ``observe_k`` is 3 or, with fewer other cars, all of
        them (2 agents + 1 adversary: 2); the varying belt's top speed is 2 within treadmill_speed … max_speed."""
        if not isinstance(data, dict):
            return data
        fields = cls.model_fields

        def value(name: str) -> int:
            return int(data.get(name, fields[name].default))

        try:
            if "observe_k" not in data:
                cars = value("n_agents") + value("n_adversaries")
                data = {**data, "observe_k": max(1, min(fields["observe_k"].default, cars - 1))}
            if "treadmill_speed_max" not in data:
                top = min(max(fields["treadmill_speed_max"].default, value("treadmill_speed")), value("max_speed"))
                data = {**data, "treadmill_speed_max": top}
        except (TypeError, ValueError):
            return data  # the field validators say what is wrong with them
        return data

    @model_validator(mode="after")
    def _consistent(self) -> TreadmillConfig:
        if self.n_cars < 2:
            raise ConfigError(
                "n_adversaries",
                "the reward is the distance to the closest other car, so at least 2 cars are needed: "
                "set n_agents + n_adversaries ≥ 2",
            )
        if self.n_agents > self.spawn_slots:
            raise ConfigError(
                "n_agents",
                f"{self.n_agents} agents do not fit the {self.spawn_slots} spawn cells in the middle half of a "
                f"{self.length} × {self.width} road with spawn_gap {self.spawn_gap}: allowed range 1 ≤ n_agents ≤ "
                f"{self.spawn_slots}; use fewer agents, a bigger road or a smaller spawn_gap",
            )
        if self.sighting_headings and not self.team_sightings:
            raise ConfigError("sighting_headings", "adds headings to the told sightings: set team_sightings=true too")
        for name in ("treadmill_speed", "initial_speed"):
            if getattr(self, name) > self.max_speed:
                raise ConfigError(name, f"must be ≤ max_speed ({self.max_speed}); allowed range 0 ≤ {name} ≤ max_speed")
        if self.treadmill_speed_max is not None and not (
            self.treadmill_speed <= self.treadmill_speed_max <= self.max_speed
        ):
            raise ConfigError(
                "treadmill_speed_max",
                f"must lie in treadmill_speed … max_speed ({self.treadmill_speed} … {self.max_speed})",
            )
        if self.adversary_speed is not None and self.adversary_speed < 1:
            raise ConfigError("adversary_speed", "a chaser must be able to move: set it ≥ 1 or leave it unset")
        if self.observe_k > self.n_cars - 1:
            raise ConfigError(
                "observe_k",
                f"an agent can observe at most the {self.n_cars - 1} other cars; "
                f"allowed range 1 ≤ observe_k ≤ n_agents + n_adversaries − 1",
            )
        if self.spawn_gap > min(self.length, self.width):
            raise ConfigError("spawn_gap", f"must be ≤ min(length, width) = {min(self.length, self.width)}")
        return self


# The second rule set, the defaults before the current ones (``--set`` each to reproduce a result measured on them):
# a 20-cell sensor over the closest car, agents spawning forward, a belt at constant speed, aggression 0.7. On them an
# open-loop weaving cycle beats the scripted driver and what teammates observe is worth nothing to a tuned driver
# (docs/treadmill.md).
V2_RULES: dict = {
    "sensor_range": 20.0,
    "observe_k": 1,
    "spawn_heading_spread": 0,
    "treadmill_speed_max": None,
    "treadmill_switch_prob": 0.0,
    "aggression": 0.7,
}

# The charger rules (docs/treadmill.md, "A hidden chaser too fast to steer"): a stealthy chaser at speed 7 that
# cannot steer above speed 3. The rules the learner study and Fig. 3's real budget train on.
CHARGER_RULES: dict = {"adversary_speed": 7, "adversary_steer_speed": 3, "adversary_stealth": True}
# What the agents are told, not how the road moves: rules that differ only here are the same rules to a reference.
INFORMATION_FIELDS: tuple[str, ...] = (
    "full_information",
    "team_observations",
    "team_sightings",
    "sighting_headings",
    "team_words",
)

RULES = 3  # the rule set the defaults are: results measured on another one are flagged (docs/reproduction.md)
N_HEADINGS = 8
# Unit move per heading, counter-clockwise from "forward along the road".
DX = np.array([1, 1, 0, -1, -1, -1, 0, 1], dtype=np.int64)
DY = np.array([0, 1, 1, 1, 0, -1, -1, -1], dtype=np.int64)
N_ACTIONS = 9  # (steer −45°, 0, +45°) × (decelerate, keep, accelerate)
# lateral position, heading one-hot, speed, distance to both side edges, longitudinal position on the treadmill
OWN_FEATURES = 1 + N_HEADINGS + 1 + 2 + 1
LONGITUDINAL = OWN_FEATURES - 1
NEIGHBOUR_FEATURES = 1 + 2 + N_HEADINGS + 1  # seen flag, relative position / sensor_range, heading one-hot, speed
FULL_FEATURES = 4  # per other car: relative position / road size, speed, adversary flag
SIGHTING_FEATURES = 5  # per other car: known flag, then FULL_FEATURES' features (zeros where unknown)
WORD_BITS = 16  # per teammate with team_words: its encode16 word, bit 0 first
