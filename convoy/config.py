"""The configuration every Convoy process agrees on: one pydantic model per algorithm and the job that runs it.

The CLI, the REST API (api/models.py), the actor and the learner processes all build a ``JobConfig`` the same way
(``job_config(...)``), so a bad value is rejected with the same message everywhere: the field, what was given and
the allowed range. Defaults that the paper ties to an environment (network sizes, message width, IMS iterations,
parameter sharing) are ``None`` in the algorithm models and filled in from ``ENV_DEFAULTS`` when the job is
resolved, so a user who sets them explicitly always wins.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, TypeVar, get_args

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from convoy.protocol.session import ZenohSettings
from convoy.validation import ConfigError as ConfigError  # re-exported: the API, learner and services import it here
from convoy.validation import build_config, flag_name

Device = Literal["auto", "cpu", "cuda"]  # where torch runs; auto = CUDA when present
Fraction = Annotated[float, Field(ge=0, le=1)]  # a probability, a share, a discount
DEVICES: tuple[str, ...] = get_args(Device)  # the same choices for the CLI's and the benchmarks' --device

MessageSource = Literal["sent", "predicted", "noise", "shuffled", "modal", "fixed"]
MESSAGE_SOURCES: tuple[str, ...] = get_args(MessageSource)  # what agents hear at evaluation (algos/listening.py)


T = TypeVar("T")


def resolved(value: T | None, field: str) -> T:
    """A field that the env's defaults fill (None = "the env's default") once the config is resolved."""
    if value is None:
        raise ConfigError(field, "not resolved: build algorithm configs with resolve_algo (the env's defaults)")
    return value


class AlgoConfig(BaseModel):
    """Hyper-parameters shared by every algorithm (section 6.1 of the paper unless noted)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lr: float = Field(5e-4, gt=0, le=1, description="Adam learning rate (paper: 5e-4).")
    lr_end: float | None = Field(
        None,
        ge=0,
        le=1,
        description="Learning rate at the run's last step, reached linearly from lr over the run (annealing: the "
        "policy's late changes shrink, so the last policy stays near the best one); None = lr throughout (the "
        "paper).",
    )
    batch_size: int = Field(64, ge=1, le=65536, description="Transitions per update (paper: 64).")
    gamma: Fraction = Field(0.99, description="Discount factor.")
    target_update: int = Field(200, ge=1, description="Updates between target-network syncs C (paper: 200).")
    target_tau: float = Field(
        1.0,
        gt=0,
        le=1,
        description="1 = copy the online weights into the target every target_update updates (the paper); below 1 "
        "= Polyak averaging, target ← (1 − τ)·target + τ·online after every update (target_update unused).",
    )
    policy_ema: float = Field(
        1.0,
        gt=0,
        le=1,
        description="Below 1: greedy evaluation, best.pt and every saved policy act with an exponential moving "
        "average of the online weights, avg ← (1 − τ)·avg + τ·online after every update (Polyak averaging of the "
        "evaluated policy, Nikishin et al. 2018): neighbouring Q-networks can differ by a fifth in return, their "
        "average does not swing with them. Training still acts with the online weights. 1 = the online weights.",
    )
    replay_capacity: int = Field(100_000, ge=1, description="Joint transitions kept in replay (oldest dropped).")
    learning_starts: int = Field(1_000, ge=0, description="Transitions stored before the first update.")
    replay_ratio: float = Field(
        1.0, gt=0, le=1024, description="Sampled transitions per inserted transition (updates follow the data)."
    )
    hidden: tuple[int, ...] | None = Field(
        None, description="Hidden layer widths; None = the env's default (the paper: treadmill 4096,12)."
    )
    share_params: bool | None = Field(
        None, description="One network for all agents (agent id appended to the input); None = the env's default."
    )
    layer_norm: bool = Field(
        False,
        description="Normalise every hidden layer's pre-activations (LayerNorm without learned scale): bounds the "
        "features a TD target bootstraps from, which keeps Q-learning with a fast-moving target from diverging "
        "(Gallici et al. 2024, PQN). False = plain MLPs (the paper).",
    )

    match_parameters: str | None = Field(
        None,
        description="A control for network size: widen every hidden layer by one factor, the least that gives this "
        "algorithm at least as many parameters as the named one's on the same env and settings (independent DQN "
        "with 'ma-mesn': as big as MA-MeSN's two networks); None = the widths as given.",
    )

    @property
    def widths(self) -> tuple[int, ...]:
        """The hidden widths once resolved (``resolve_algo`` fills ``hidden`` from the env's defaults)."""
        return resolved(self.hidden, "hidden")

    advantage_learning: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="Advantage learning α (Bellemare et al. 2016): the TD target subtracts α·(max_b Q̄(s, b) − "
        "Q̄(s, a)) with the target network Q̄, widening the gap between the best action and the rest so that the "
        "greedy policy stops flipping on small Q errors; 0 = plain Q-learning (the paper). Not applied by DIAL.",
    )
    n_step: int = Field(
        1,
        ge=1,
        le=64,
        description="Multi-step returns (Sutton 1988; Rainbow): a transition's target sums up to n steps of "
        "discounted reward, stopping at the episode's end or its chunk's (4·n steps), and "
        "bootstraps with γ^m for the m steps it spans. A frozen target network lets value travel one step per "
        "sync; n-step, n steps. 1 = one-step Q-learning (the paper). Not DIAL or hierarchical DQN.",
    )
    double_q: bool = Field(True, description="Double Q-learning: online argmax, target value (paper: on).")
    huber: bool = Field(True, description="Huber TD loss (clipped error) instead of the squared TD error.")
    grad_clip: float = Field(10.0, gt=0, description="Global gradient-norm clip.")
    compile: bool = Field(
        False,
        description="Capture each update from its sampled batch on (loss, gradients, clip, non-finite guard, Adam, "
        "Polyak target and policy average) as one graph, torch.compile(fullgraph=True): fewer, fused kernels; the "
        "first update compiles (tens of seconds on a CPU) and a graph break is an error. False = eager updates.",
    )
    eps_start: Fraction = Field(1.0, description="Exploration ε at step 0.")
    eps_end: Fraction = Field(0.05, description="Exploration ε after the decay (paper: 0.05).")
    eps_decay_fraction: float = Field(0.2, gt=0, le=1, description="ε decays over this fraction of the run ...")
    eps_decay_max_steps: int = Field(100_000, ge=1, description="... or over this many env steps, if fewer.")
    eps_hold_max: int = Field(
        1,
        ge=1,
        le=10_000,
        description="Temporally extended ε-greedy (εz-greedy, Dabney et al. 2021): an agent that explores repeats "
        "its random action for n steps, n drawn from P(n) ∝ n^−eps_hold_mu on 1 … eps_hold_max, then acts "
        "greedily again; 1 = ε-greedy one step at a time (the paper).",
    )
    eps_hold_mu: float = Field(2.0, gt=0, le=10, description="The exponent μ of εz-greedy's hold lengths (paper: 2).")

    @field_validator("hidden", mode="before")
    @classmethod
    def _one_layer(cls, v: Any) -> Any:
        return (v,) if isinstance(v, int) else v

    @model_validator(mode="after")
    def _check(self) -> AlgoConfig:
        if self.batch_size > self.replay_capacity:
            raise ConfigError(
                "batch_size",
                f"{self.batch_size} is larger than replay_capacity {self.replay_capacity}; "
                "lower batch_size or raise replay_capacity",
            )
        if self.hidden is not None and (not self.hidden or min(self.hidden) < 1):
            raise ConfigError("hidden", f"needs at least one layer of ≥ 1 unit (got {self.hidden!r})")
        return self

    @field_validator("match_parameters")
    @classmethod
    def _an_algorithm(cls, v: str | None) -> str | None:
        try:
            return None if v is None else algo_name(v)
        except ConfigError as exc:  # named as this field, not as --algo
            raise ConfigError("match_parameters", str(exc).split(": ", 1)[-1]) from None


class MessageConfig(AlgoConfig):
    """Algorithms that send discrete messages of a fixed width."""

    message_bits: int | None = Field(
        None, ge=1, le=256, description="Binary symbols per message; None = env default (2 bytes = 16)."
    )


class GumbelConfig(MessageConfig):
    """Messages as Gumbel-softmax bits, straight-through in training, argmax at execution (DIAL has its DRU)."""

    gumbel_tau: float = Field(1.0, gt=0, le=100, description="Gumbel-softmax temperature.")
    gumbel_noise: float | None = Field(
        None,
        ge=0,
        le=10,
        description="Gumbel noise scale in training: 1 = sampled messages, 0 = deterministic straight-through; "
        "None = env default (0 on speaker-listener, where the paper used a plain softmax, and on the treadmill; "
        "else 1).",
    )
    message_logit_bound: float | None = Field(
        None,
        gt=0,
        le=100,
        description="Bound each bit's logit difference to (−b, b) with b·tanh(d/b) so messages cannot saturate "
        "(a saturated bit is constant and its gradient ~e^−|d| never reopens it); None = unbounded (the paper).",
    )
    signalling_coef: float = Field(
        0.0,
        ge=0,
        le=100,
        description="Weight of the positive-signalling term (MA-MeSN, MA-BoN, discrete IMS): the loss subtracts "
        "coef × I(observation; message), estimated per batch, so messages stay informative instead of collapsing "
        "onto one codeword; 0 = off (the paper).",
    )


class EntityFields(BaseModel):
    """How a network reads the observation and gives its Q-values (independent DQN and the MA-MeSN / MA-BoN
    networks)."""

    encoder: Literal["mlp", "entity"] = Field(
        "mlp",
        description="How the networks read the observation: mlp = one MLP over the flat vector (the paper); entity = "
        "one encoder shared by every car, applied alike to the agent's sensor slots, the sightings it is told and "
        "(MA-MeSN, MA-BoN listeners) each heard message, pooled by a masked sum and max (slot order and empty slots "
        "change nothing), beside an embedding of the agent's own features, then the Q head of the hidden widths. "
        "entity needs an env whose observation is laid out as cars (the treadmill).",
    )
    entity_width: int = Field(
        64, ge=1, le=4096, description="Units of each car's (and message's) embedding and of the own-feature one."
    )
    entity_context: bool = Field(
        False,
        description="With encoder=entity: the per-car encoder also reads the agent's own features (position, "
        "heading, speed) beside each car's token, so it can judge that car against the agent's own motion (a car "
        "closing in on its line) before the pooling mixes the cars; False = each car read alone.",
    )
    dueling: bool = Field(
        False,
        description="Dueling Q head (Wang et al. 2016): the last layer gives a state value V and one advantage A_a "
        "per action, Q_a = V + A_a − mean_b A_b, so every TD error moves the value of every action in that state.",
    )


DEMONSTRABLE = ("idqn", "dqn-ser", "ma-mesn", "ma-bon")  # feed-forward learners a demonstrator can start


MAX_DEMO_ROUNDS = 64  # DAgger rounds of a demonstrator start (a learner reports each: services/jobrunner.py)


class DemonstrationFields(BaseModel):
    """A start from a planner's demonstrations (independent DQN, DQN-SER, MA-MeSN, MA-BoN; learner/imitation.py)."""

    demonstrator: str | None = Field(
        None,
        max_length=64,
        description="A treadmill reference policy (convoy env rollout --policy's names; planner = the planner of the "
        "learner's information: team-planner when told teammates' sightings or observations, team16-planner when "
        "told their words or hearing teammates over an open channel (MA-MeSN, MA-BoN), else private-planner) "
        "cloned into the Q-network by DAgger (MA-MeSN, MA-BoN: into speakers and listeners together, through the "
        "channel) "
        "before Q-learning starts (learner/imitation.py): demo_rounds rounds of demo_episodes tuning episodes per "
        "run, the env steps they take reported beside the run's steps (demonstration.json). Start Q-learning gently "
        "(eps_start=0.05, learning_starts=20000) or it unlearns the clone. None = from scratch (the paper).",
    )
    demo_rounds: int = Field(8, ge=1, le=MAX_DEMO_ROUNDS, description="DAgger rounds of a demonstrator start.")
    demo_episodes: int = Field(
        128, ge=1, le=4096, description="Tuning episodes each run plays per DAgger round (its own states)."
    )
    demo_epochs: int = Field(
        4, ge=1, le=100, description="Passes over a run's states so far after each DAgger round (cross-entropy)."
    )
    demo_margin: float = Field(
        0.0,
        ge=0.0,
        le=100.0,
        description="Weight λ of DQfD's large-margin loss (Hester et al. 2018) on the DAgger states during "
        "Q-learning: each update also draws batch_size of them and asks the teacher's action to lead every other "
        "Q-value by 0.8, so that Q-learning keeps what the clone learned where TD gives no reason to change it "
        "(the states are kept on the training device and in the replay file). 0 = off.",
    )

    @model_validator(mode="after")
    def _margin_on_demonstrations(self) -> DemonstrationFields:
        if self.demo_margin > 0 and not self.demonstrator:
            raise ConfigError("demo_margin", "a margin on demonstrations needs a demonstrator: set demonstrator="
                              "planner (or --preset charger-demo), or leave demo_margin at 0")  # fmt: skip
        return self


class IDQNConfig(AlgoConfig, EntityFields, DemonstrationFields):
    """Independent DQN: every agent learns from its own observation only."""

    heads: int = Field(
        1,
        ge=1,
        le=32,
        description="Bootstrapped DQN (Osband et al. 2016): K Q-heads, each its own MLP of the hidden widths on the "
        "shared encoder, each learning from every sample with its own double-Q target; an exploring env (ε > 0) "
        "drives a whole episode on one head drawn at its start, an evaluation (ε = 0) on the heads' mean Q. "
        "Needs share_params. 1 = one Q-network (the paper).",
    )
    priority_alpha: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Prioritized replay (Schaul et al. 2016, as in Rainbow): a joint transition is drawn with "
        "probability ∝ (|δ| + 0.001)^α, δ its TD error averaged over the agents at its last draw (a new one at the "
        "largest priority its run has had), and its loss weighted by (N·P)^−β over the batch's largest, so that the "
        "rare transitions the network gets most wrong (a crash) are learned from often; 0 = uniform draws (the "
        "paper).",
    )
    priority_beta: float = Field(
        0.4,
        ge=0,
        le=1,
        description="Prioritized replay's importance-sampling exponent β at the run's start, annealed linearly to 1 "
        "at its end (Schaul et al.: the bias of non-uniform draws matters most near convergence).",
    )


class SERConfig(IDQNConfig):
    """DQN with stabilised experience replay (the paper's linearly decaying per-sample weight)."""

    ser_horizon: int = Field(
        200, ge=1, description="Episodes after which a sample's weight reaches 0 (weight = 1 − age/horizon)."
    )
    fingerprint: bool = Field(False, description="Append Foerster et al.'s fingerprint (ε, training progress).")


class DIALConfig(MessageConfig):
    """DIAL: one network gives Q-values and a message; DRU noise in training; messages arrive one step late.

    On-policy (the default), every chunk of ``unroll`` steps gets exactly one update, so ``batch_size``,
    ``learning_starts``, ``replay_ratio`` and ``target_update`` do not apply; targets sync every
    ``target_update_episodes`` finished episodes instead. With ``replay`` an update draws ``batch_size`` sequences
    of ``unroll`` steps from a ring of ``replay_capacity // unroll`` sequences.
    """

    dru_sigma: float = Field(2.0, ge=0, description="Std of the Gaussian noise the DRU adds in training (paper: 2).")
    unroll: int = Field(32, ge=1, le=4096, description="Steps per on-policy sequence batch (truncated BPTT).")
    target_update_episodes: int = Field(40, ge=1, description="Episodes between target syncs (paper: 40).")
    replay: bool = Field(
        False,
        description="Importance-sampled sequence replay (the paper's variant for particle envs): batch_size "
        "sequences of unroll steps per update, each step's loss weighted by a clipped importance ratio.",
    )


class IMSConfig(GumbelConfig):
    """IMS / CommNet: P rounds of messages averaged over the other agents."""

    comm_iterations: int | None = Field(
        None, ge=1, le=64, description="Communication iterations P; None = env default (treadmill 5, predator-prey 3)."
    )
    discrete: bool = Field(
        True,
        description="Messages are message_bits Gumbel-softmax bits (the paper's 2-byte cap); False = CommNet's "
        "original continuous messages (message_bits real values per message, not quantised).",
    )


class ChannelControl(BaseModel):
    """The controls a communication claim is judged against: the same networks, trained without a channel."""

    channel_control: Literal["open", "cut", "noise"] = Field(
        "open",
        description="What every listener hears, in training and at execution: open = the messages (the paper); cut "
        "= all-zero bits (the channel-cut twin: a gain over it is the messages', not the second network's); noise = "
        "uniformly random bits drawn afresh at every step.",
    )
    speakers_learn: bool = Field(
        True,
        description="Q-learning's TD gradients reach the message networks (Algorithm 1: every listener's loss "
        "trains each speaker). False trains the listeners only and keeps the speakers as they start: with a "
        "demonstrator, the protocol DAgger taught, which then cannot drift while the listeners learn its values.",
    )


class MeSNConfig(GumbelConfig, ChannelControl, EntityFields, DemonstrationFields):
    """MA-MeSN (Algorithm 1): separate message networks f′ and policy networks f″."""


class BoNConfig(GumbelConfig, ChannelControl, EntityFields, DemonstrationFields):
    """MA-BoN: one broadcast message from all agents' encodings."""

    encoding: int = Field(64, ge=1, le=65536, description="Width of each agent's observation encoding.")
    agent_id: bool = Field(
        True,
        description="With shared weights, append a one-hot agent id to the encoder and g′ inputs so roles can "
        "differ; False = the paper's g′(z_i, bm), whose size is then independent of the number of agents.",
    )


class MemoryFields(BaseModel):
    """The LSTM memory module of the ``-mm`` variants (section 4.1: decentralised execution without a channel)."""

    memory_window: int = Field(
        8, ge=1, le=256, description="Own observations (this step and the ones before) the memory module reads."
    )
    memory_hidden: int = Field(128, ge=1, le=65536, description="LSTM units of each agent's memory module.")
    memory_coef: float = Field(1.0, gt=0, le=1000, description="Weight of the message-prediction loss (BCE).")


class MeSNMMConfig(MeSNConfig, MemoryFields):
    """MA-MeSN-MM: MA-MeSN plus a memory module per agent predicting the messages it hears."""


class BoNMMConfig(BoNConfig, MemoryFields):
    """MA-BoN-MM: MA-BoN plus a memory module per agent predicting the broadcast message."""


class CoDBCConfig(AlgoConfig):
    """CoDBC: per-agent behaviour cloning of a trained centralised policy (run after it, as the paper does)."""

    teacher: str | None = Field(
        None, description="Checkpoint of the trained centralised policy to clone (e.g. runs/ma-mesn/checkpoint.pt)."
    )
    teacher_fraction: Fraction = Field(
        1.0,
        description="Share of envs the teacher drives at step 0, decaying linearly to 0 with ε (DAgger's β); "
        "the student drives the rest, and the teacher labels every visited state.",
    )

    @model_validator(mode="after")
    def _teacher(self) -> CoDBCConfig:
        if not self.teacher:
            raise ConfigError(
                "teacher",
                "CoDBC clones a trained centralised policy: set algo_params teacher=PATH to its checkpoint "
                "(train one first, e.g. `convoy train --algo ma-mesn`)",
            )
        return self


@dataclass(frozen=True)
class Algorithm:
    """One row of the algorithm table: everything the rest of Convoy needs to know about an algorithm by name."""

    config: type[AlgoConfig]  # its hyper-parameters (CLI flags, REST bodies and defaults come from this model)
    impl: str  # ``module:Class`` of its implementation, imported on first use (``convoy.algos.registry``)
    summary: str  # one line for ``--help`` and the catalog
    listens: bool = False  # it hears discrete per-agent messages that an evaluation may replace (noise, predicted)
    needs_messages: bool = False  # it cannot act without its teammates' messages (no "predicted" evaluation)


# The one table of algorithms: adding one is a row here and its module under algos/ (docs/algorithms.md).
ALGORITHMS: dict[str, Algorithm] = {
    "idqn": Algorithm(IDQNConfig, "convoy.algos.idqn:IndependentDQN", "independent DQN, no communication"),
    "dqn-ser": Algorithm(SERConfig, "convoy.algos.dqn_ser:DQNSER",
                         "independent DQN with stabilised experience replay (+ fingerprint option)"),
    "dial": Algorithm(DIALConfig, "convoy.algos.dial:DIAL",
                      "DIAL: differentiable inter-agent learning, DRU messages from t−1", needs_messages=True),
    "ims": Algorithm(IMSConfig, "convoy.algos.ims:IMS", "IMS / CommNet: P iterations of averaged messages",
                     needs_messages=True),
    "ma-mesn": Algorithm(MeSNConfig, "convoy.algos.ma_mesn:MAMeSN",
                         "MA-MeSN: message networks + policy networks (Algorithm 1)", listens=True,
                         needs_messages=True),
    "ma-bon": Algorithm(BoNConfig, "convoy.algos.ma_bon:MABoN", "MA-BoN: one broadcast message, all agents in one pass",
                        listens=True, needs_messages=True),
    "ma-mesn-mm": Algorithm(MeSNMMConfig, "convoy.algos.ma_mesn_mm:MAMeSNMM",
                            "MA-MeSN + LSTM memory modules: runs with no channel (decentralised)", listens=True),
    "ma-bon-mm": Algorithm(BoNMMConfig, "convoy.algos.ma_bon_mm:MABoNMM",
                           "MA-BoN + LSTM memory modules: runs with no channel (decentralised)", listens=True),
    "codbc": Algorithm(CoDBCConfig, "convoy.algos.codbc:CoDBC",
                       "CoDBC: per-agent behaviour cloning of a trained centralised policy"),
}  # fmt: skip

# Per environment: what the paper fixes (network sizes, message width, IMS iterations, sharing) and the training
# settings measured to work there (docs/training.md); applied to every field the user does not set.
ENV_DEFAULTS: dict[str, dict[str, Any]] = {
    "treadmill": {  # docs/training.md has the measurements behind the training settings
        "hidden": (256, 256),  # the paper's (4096, 12) learns nothing in our budgets (docs/training.md)
        "message_bits": 16,
        "comm_iterations": 5,
        # deterministic straight-through bits: with Gumbel noise MA-MeSN declined after ~100 k steps like independent
        # DQN, without it not (docs/training.md, the figures in docs/benchmarks.md)
        "gumbel_noise": 0.0,
        "share_params": True,
        "lr": 1e-4,
        "batch_size": 128,
        "replay_ratio": 32.0,
        "replay_capacity": 1_000_000,
        # 1,000 collapsed every seed of independent DQN once ε fell; 8,000 holds all five at or above their best
        # point (docs/benchmarks.md#treadmill-learners has the figures)
        "target_update": 8_000,
        "gamma": 0.95,
        "eps_end": 0.01,
        "eps_decay_fraction": 1.0,
        "eps_decay_max_steps": 10_000_000,
        "signalling_coef": 0.0,  # deterministic messages stay varied without it (3.05 nats at 300 k)
        "advantage_learning": 0.9,
    },
    "predator-prey": {
        "hidden": (256,),
        "message_bits": 8,
        "comm_iterations": 3,
        "gumbel_noise": 1.0,
        "share_params": True,
    },
    "speaker-listener": {
        "hidden": (256,),
        "message_bits": 2,
        "comm_iterations": 1,
        "gumbel_noise": 0.0,
        "share_params": False,
    },
    "referential": {
        "hidden": (256,),
        "message_bits": 16,
        "comm_iterations": 1,
        "gumbel_noise": 1.0,
        "share_params": False,
    },
}
# Where the paper gives one algorithm a different default on one env (section 6.1: DIAL's first layer is 6144 wide
# on the treadmill, "to allow for fair evaluation to other algorithms").
# Scaled with our treadmill width: 1.5× the first layer of the others, as 6144 is to 4096.
# IMS runs its P = 5 rounds on the last layer, as the paper's do on its 12 units: on 256 units an update costs 3.3×
# one on 64 (56 vs 17 ms) and a 300 k run 55 min, past the treadmill's 30-minute budget (docs/benchmarks.md).
ALGO_ENV_DEFAULTS: dict[tuple[str, str], dict[str, Any]] = {
    ("dial", "treadmill"): {"hidden": (384, 256)},
    ("ims", "treadmill"): {"hidden": (256, 64)},
}


# The paper's treadmill networks (section 6.1), kept for the benchmarks that measure cost at the paper's sizes.
PAPER_TREADMILL_HIDDEN: tuple[int, ...] = (4096, 12)
PAPER_DIAL_TREADMILL_HIDDEN: tuple[int, ...] = (6144, 12)


def paper_treadmill_hidden(algo: str) -> tuple[int, ...]:
    """The hidden widths the paper gives ``algo`` on the treadmill."""
    return PAPER_DIAL_TREADMILL_HIDDEN if algo_name(algo) == "dial" else PAPER_TREADMILL_HIDDEN


# Named starting points of a job (``preset``): env rules and learner settings, under whatever the job sets itself.
# "charger": the hidden charger too fast to steer (envs/treadmill/config.py's CHARGER_RULES, where teammates'
# knowledge pays the planners) and the learner recipe measured there (docs/treadmill.md, "Learners on the charger
# rules"): entity encoder, 3-step returns, squared TD error, LayerNorm, a Polyak target, ε over half the run, the
# learning rate annealed to 0, the averaged policy judged. A setting an algorithm has no field for is left out.
# "charger-demo": the same, started from the planner of the learner's information (``demonstrator=planner``, DAgger;
# learner/imitation.py) and Q-learning gently from there (ε from 0.05, updates after 20 k steps) — where the learner
# can take a demonstration (DEMONSTRABLE); any other algorithm gets "charger". "charger-dqfd": charger-demo with
# DQfD's margin on the demonstrations through Q-learning (``demo_margin=1``), which keeps what DAgger taught a
# communicating learner (docs/treadmill.md, "DQfD's margin keeps it").
_CHARGER = {"encoder": "entity", "n_step": 3, "huber": False, "layer_norm": True, "target_tau": 0.001, "lr_end": 0.0,
            "policy_ema": 0.0001, "eps_decay_fraction": 0.5}  # fmt: skip
PRESET_ALGO_PARAMS: dict[str, dict[str, Any]] = {
    "charger": _CHARGER,
    "charger-demo": {**_CHARGER, "demonstrator": "planner", "eps_start": 0.05, "learning_starts": 20_000},
}
PRESET_ALGO_PARAMS["charger-dqfd"] = {**PRESET_ALGO_PARAMS["charger-demo"], "demo_margin": 1.0}
DEMO_PRESETS = ("charger-demo", "charger-dqfd")  # presets that start from a demonstrator where the learner can
Preset = Literal["charger", "charger-demo", "charger-dqfd"]


def preset_settings(name: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """Everything preset ``name`` sets, (env_params, algo_params), whatever the algorithm takes of it."""
    from convoy.envs.treadmill.config import CHARGER_RULES

    return dict(CHARGER_RULES), dict(PRESET_ALGO_PARAMS[name])  # every preset's rules


def preset_params(name: str, algo: str, hierarchical: bool = False) -> tuple[dict[str, Any], dict[str, Any]]:
    """The preset's (env_params, algo_params) for ``algo``: its settings the algorithm has a field for (no n-step
    returns where sequences or options are learned: DIAL, hierarchical DQN). DIAL keeps its own target sync (by
    episodes) and judges its online weights: it updates once per batch of unrolled sequences (782 updates in a
    400 k-step on-policy run, ~3 k replayed, against ~10⁵ for a learner replaying single steps), and the preset's
    per-update averaging rates were set for ~10⁵: in 782 updates a Polyak target at τ = 0.001 moves half way to the
    online weights, the judged average at 1e-4 under a tenth of the way."""
    if name in DEMO_PRESETS and (hierarchical or algo_name(algo) not in DEMONSTRABLE):
        name = "charger"  # no demonstration to start from: nor its gentle start
    env_params, settings = preset_settings(name)
    fields = ALGORITHMS[algo_name(algo)].config.model_fields
    dial = algo_name(algo) == "dial"
    left_out = ({"n_step"} if hierarchical or dial else set()) | ({"target_tau", "policy_ema"} if dial else set())
    return env_params, {k: v for k, v in settings.items() if k in fields and k not in left_out}


def env_name(name: str) -> str:
    """Canonical env name (any name ``env_entry`` takes), or its ConfigError."""
    from convoy.envs.registry import env_entry

    entry = env_entry(name)
    return next(k for k, v in _env_table().items() if v is entry)


def algo_name(name: str) -> str:
    """Canonical algorithm name (case and ``_`` forgiven), or a ConfigError listing the known ones."""
    key = name.strip().lower().replace("_", "-")
    if key not in ALGORITHMS:
        raise ConfigError("algo", f"unknown algorithm {name!r}; choose one of: {', '.join(ALGORITHMS)}")
    return key


class ResourceLimits(BaseModel):
    """What one job may ask of the machine that trains it, checked before anything is allocated: asks past these
    are typos that would crash-loop allocating (``hidden: [1e9]`` wants ~100 GB). ``convoy serve`` and ``convoy
    train`` take each field as a flag (``--max-layer-width``, ...); the defaults fit a laptop: ~5× the paper's
    widest layer (DIAL's 6144), ~1 GB of fp32 weights + Adam state between hidden layers."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_layer_width: int = Field(32_768, ge=1, description="units in any hidden layer")
    max_hidden_weights: int = Field(64_000_000, ge=1, description="weights between consecutive hidden layers, summed")
    max_agent_envs: int = Field(
        1_048_576, ge=1, description="num_envs × agents per env, stepped by one process (an actor, or in-process)"
    )

    def check(self, job: JobConfig, command: str) -> None:
        """A ConfigError naming the job's field, the limit and ``command``'s flag that raises it."""
        hidden = tuple(job.algo_config().hidden or ())
        weights = sum(a * b for a, b in itertools.pairwise(hidden))
        agents, runs = job.agents_per_env(), job.runs or 1
        envs = f"{job.num_envs:,} envs × {agents:,} agents" + (f" × {runs} runs" if runs > 1 else "")
        asks = [
            ("algo_params.hidden", "max_layer_width", max(hidden, default=0), f"{max(hidden, default=0):,} units"),
            ("algo_params.hidden", "max_hidden_weights", weights * runs, f"{weights * runs:,} weights between hidden "
             "layers" + (f" ({runs} runs)" if runs > 1 else "")),
            ("num_envs", "max_agent_envs", job.num_envs * agents * runs, envs),
        ]  # fmt: skip
        for field, limit, value, what in asks:
            bound = getattr(self, limit)
            if value > bound:
                flag = flag_name(limit)
                raise ConfigError(
                    field,
                    f"{what} is over this {command}'s limit {limit} = {bound:,}; ask for less (the paper's treadmill "
                    f"network is [4096, 12]), or raise the limit with {command} {flag} N",
                )


def env_defaults(algo: str, env: str) -> dict[str, Any]:
    """The hyper-parameters ``env`` sets for ``algo`` where the user sets nothing."""
    key = algo_name(algo)
    defaults = {**ENV_DEFAULTS.get(env, ENV_DEFAULTS["referential"]), **ALGO_ENV_DEFAULTS.get((key, env), {})}
    return {k: v for k, v in defaults.items() if k in ALGORITHMS[key].config.model_fields}


def env_default_note(field: str) -> str:
    """``"; treadmill 0.0001"``: where an env's default of ``field`` differs from the model's (for ``--help``)."""
    notes = [f"{env} {_show(d[field])}" for env, d in ENV_DEFAULTS.items() if field in d]
    notes += [f"{a} on {env} {_show(d[field])}" for (a, env), d in ALGO_ENV_DEFAULTS.items() if field in d]
    return f"; {', '.join(notes)}" if notes else ""


def _show(value: Any) -> str:
    return ",".join(map(str, value)) if isinstance(value, tuple) else repr(value)


def resolve_algo(algo: str, env: str, params: dict[str, Any] | None = None) -> AlgoConfig:
    """The algorithm's validated config: what the user set, and the env's defaults for everything else."""
    given = {k: v for k, v in (params or {}).items() if v is not None}
    return build_config(ALGORITHMS[algo_name(algo)].config, **{**env_defaults(algo, env), **given})


class RuntimeConfig(BaseModel):
    """How the distributed runtime runs a job (ignored by ``--inprocess``): processes, flow control, transport."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    actors: int = Field(2, ge=1, le=256, description="Actor processes, each stepping num_envs envs.")
    publish_steps: int = Field(
        8, ge=1, le=4096, description="Env steps per published chunk (DIAL: its unroll; one sequence per chunk)."
    )
    weights_every: int = Field(10, ge=1, description="Learner updates between weight broadcasts (also every 1 s).")
    epsilon_spread: float = Field(
        0.0,
        ge=0,
        le=16,
        description="Ape-X ε spread α: actor i of N explores with ε(t)^(1 + α·i/(N−1)); 0 = all follow ε(t).",
    )
    slack_steps: int | None = Field(
        None,
        ge=1,
        description="Env steps actors may run ahead of the learner before they wait; None = 2 chunks per actor "
        "(more slack, more policy lag).",
    )
    actor_nice: int = Field(
        5,
        ge=0,
        le=19,
        description="Niceness added to actor processes: where actors and the learner share cores, the learner (one "
        "per job, what every actor waits for) gets the larger CPU share; 0 = equal shares.",
    )
    actor_device: Device = Field(
        "cpu", description="Torch device of actors' inference (small batches: CPU unless envs are many)."
    )
    inbox: int = Field(256, ge=1, description="Chunks the learner queues off the Zenoh thread (oldest dropped).")
    max_restarts: int = Field(
        5, ge=0, description="Learner crashes within restart_window_s before the job fails with the reason."
    )
    actor_max_restarts: int = Field(
        100,
        ge=0,
        description="Actor deaths within restart_window_s before the job fails: generous, as actors come and go "
        "(killed, out of memory, a host lost) while the learner is healthy; a crash loop is slowed by "
        "restart_backoff_s instead (RLlib restarts env runners up to 1000 times).",
    )
    restart_window_s: float = Field(60.0, gt=0, le=86_400, description="Window for max_restarts.")
    restart_backoff_s: float = Field(
        0.5,
        ge=0,
        le=60,
        description="Delay before respawning an actor that died within 10 s of its start; doubles with each such "
        "death of the same actor in a row (at most 30 s). An actor that ran longer is respawned at once.",
    )
    data_timeout_s: float = Field(
        600.0,
        gt=0,
        le=604_800,
        description="The learner gives up (checkpoint, then exit with the reason) when no chunk has come for this "
        "long: a job whose actors are all gone must not wait for ever.",
    )
    replay_checkpoint_mb: int = Field(
        8192,
        ge=0,
        description="A run saves its replay buffer (replay.npz beside checkpoint.pt) with each checkpoint while it "
        "holds at most this many MB, so a restarted learner or `convoy train --resume` goes on with its data "
        "instead of an empty buffer (over it, the checkpoint says so); 0 = never. A treadmill row is 1.2–2.2 KB "
        "(own observation – told sightings): 8192 MB keeps five 400 k-step runs' rows.",
    )
    keep_replay: bool = Field(
        False,
        description="Keep replay.npz when the run completes (to resume it past its budget with its data); by default "
        "a completed run deletes it: it can be gigabytes, and only an unfinished run needs it.",
    )
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings, description="Zenoh session (peer on loopback).")

    def chunk_len(self, algo_chunk_len: int) -> int:
        """Env steps per published chunk: the algorithm's own sequence length where it has one (DIAL's unroll),
        else ``publish_steps``."""
        return algo_chunk_len if algo_chunk_len > 1 else self.publish_steps

    def slack(self, num_envs: int, chunk_len: int) -> int:
        """``slack_steps``, or two chunks per actor: enough to keep actors busy while the learner takes in a chunk,
        small enough that queued data does not age into policy lag (4096 steps gave ~70 updates of lag). Never less
        than one chunk, which an actor sends whole: a smaller slack would never let it send."""
        return max(self.slack_steps or 2 * self.actors * chunk_len * num_envs, chunk_len * num_envs)


MAX_POPULATION = 256  # runs of one population: what one learner's memory and one weights message can hold


class JobConfig(BaseModel):
    """One training job: which algorithm on which env, for how long, and how to report."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    ALGOS: ClassVar[tuple[str, ...]] = tuple(ALGORITHMS)

    algo: str = Field("ma-mesn", max_length=32, description=f"Algorithm: {', '.join(ALGORITHMS)}.")
    env: str = Field("treadmill", max_length=32, description="Environment name (see `convoy env list`).")
    env_params: dict[str, Any] = Field(default_factory=dict, description="Environment parameters.")
    algo_params: dict[str, Any] = Field(default_factory=dict, description="Algorithm hyper-parameters.")
    preset: Preset | None = Field(
        None,
        description="Start from named env rules and learner settings; env_params and algo_params set on top win. "
        "charger: the treadmill's hidden charger too fast to steer and the learner recipe measured on it "
        "(docs/treadmill.md); charger-demo: the same, started from the planner of the learner's information "
        "(demonstrator=planner) where the algorithm can take one; charger-dqfd: charger-demo with DQfD's margin on "
        "the demonstrations through Q-learning (demo_margin=1)",
    )
    hierarchical: bool = Field(False, description="Hierarchical DQN (appendix A.2): goals + controller; treadmill.")
    steps: int = Field(
        200_000,
        ge=1,
        le=1_000_000_000,
        description="Total env steps (summed over parallel envs); a run ends at the first chunk boundary at or "
        "past it, so it may exceed it by less than one chunk per actor (num_envs × runtime.publish_steps).",
    )
    num_envs: int = Field(16, ge=1, le=65536, description="Envs stepped together per actor.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed of envs, exploration and network init.")
    seeds: list[int] = Field(
        default_factory=list,
        max_length=MAX_POPULATION,
        description="A population: one run per seed, trained together (one batched update for all; run k writes "
        "DIR/seed-N as the single run of its seed would); instead of seed. Empty: the single run of seed.",
    )
    eval_episodes: int = Field(
        100,
        ge=0,
        le=10_000,
        description="Greedy episodes per evaluation (fixed seeds): each learning-curve point and the final one.",
    )
    eval_messages: MessageSource = Field(
        "sent",
        description="What the agents hear in the greedy evaluations (curve and final): sent = centralised execution; "
        "predicted = decentralised, each agent's memory module predicts the messages (ma-mesn-mm, ma-bon-mm; "
        "algorithms without messages are decentralised already); noise = white noise instead of messages; shuffled, "
        "modal, fixed = the controls of `convoy eval --messages`.",
    )
    eval_every: int = Field(
        10_000,
        ge=0,
        le=1_000_000_000,
        description="Env steps between greedy evaluations, the learning curve (at metric rows); 0 = the final only.",
    )
    log_every: int = Field(2_000, ge=1, le=1_000_000_000, description="Env steps between metric rows.")
    checkpoint_every: int = Field(50_000, ge=1, le=1_000_000_000, description="Env steps between checkpoints.")
    loggers: list[Literal["wandb", "mlflow"]] = Field(
        default_factory=list,
        max_length=2,
        description="Experiment trackers besides TensorBoard (every run writes RUN/tb/): wandb, mlflow — each an "
        "optional extra (pip install 'convoy[wandb]').",
    )
    device: Device = Field("auto", description="Torch device; auto = CUDA when present.")
    torch_threads: int = Field(1, ge=1, le=256, description="Torch intra-op threads of the learner.")
    runtime: RuntimeConfig = Field(default_factory=RuntimeConfig, description="Distributed runtime settings.")

    @model_validator(mode="before")
    @classmethod
    def _apply_preset(cls, data: Any) -> Any:
        """The preset's settings under the job's own (applying it again, as a resumed job does, changes nothing)."""
        if not isinstance(data, dict) or data.get("preset") not in PRESET_ALGO_PARAMS:
            return data  # none, or one the field's own validation names the choices for
        if env_name(str(data.get("env", "treadmill"))) != "treadmill":
            raise ConfigError("preset", f"{data['preset']!r} sets treadmill rules; drop it or train on the treadmill")
        env_params, algo_params = preset_params(
            data["preset"], str(data.get("algo", "ma-mesn")), bool(data.get("hierarchical"))
        )
        given_env, given_algo = data.get("env_params") or {}, data.get("algo_params") or {}
        if not isinstance(given_env, dict) or not isinstance(given_algo, dict):
            return data  # the fields' own validation says what they must be
        return {**data, "env_params": {**env_params, **given_env}, "algo_params": {**algo_params, **given_algo}}

    @model_validator(mode="after")
    def _check(self) -> JobConfig:
        from convoy.envs.registry import env_entry

        object.__setattr__(self, "algo", algo_name(self.algo))
        object.__setattr__(self, "env", env_name(self.env))
        entry = env_entry(self.env)
        build_config(entry.config(), **self.env_params)
        model = ALGORITHMS[self.algo].config
        given = build_config(model, **self.algo_params)  # validates; then store a JSON-stable normal form
        object.__setattr__(self, "algo_params", given.model_dump(mode="json", exclude_unset=True))
        if self.steps < self.num_envs:
            raise ConfigError(
                "steps",
                f"{self.steps:,} is less than one step of the {self.num_envs:,} envs stepped together "
                f"({self.num_envs:,} env steps); raise steps or lower num_envs",
            )
        row = ALGORITHMS[self.algo]
        if self.eval_messages in ("noise", "shuffled", "modal", "fixed") and not row.listens:
            raise ConfigError(
                "eval_messages", f"{self.algo} has no message channel to replace ({self.eval_messages}); use sent"
            )
        if self.eval_messages == "predicted" and row.needs_messages:
            raise ConfigError(
                "eval_messages",
                f"{self.algo} cannot act without its teammates' messages; train ma-mesn-mm or ma-bon-mm to predict "
                "them, or use sent",
            )
        if self.hierarchical and self.env != "treadmill":
            raise ConfigError("hierarchical", f"goals are defined for the treadmill only (env is {self.env!r})")
        if self.algo_params.get("n_step", 1) != 1 and (self.hierarchical or self.algo == "dial"):
            why = "hierarchical DQN's options span many steps" if self.hierarchical else "DIAL learns from sequences"
            raise ConfigError("algo_params.n_step", f"{why}; drop n_step (one-step returns) for this job")
        self._check_seeds()
        if self.algo_params.get("demonstrator"):
            self._check_demonstrator()
        if self.algo_params.get("encoder") == "entity":
            self._check_layout()
        return self

    def _check_demonstrator(self) -> None:
        """A demonstrator is a treadmill reference cloned into a feed-forward Q-network (one head): refused where it
        could not be."""
        from convoy.envs.treadmill.references import REFERENCES

        name, field = self.algo_params["demonstrator"], "algo_params.demonstrator"
        if self.algo not in DEMONSTRABLE:
            raise ConfigError(field, f"{self.algo} cannot start from demonstrations; use one of "
                              f"{', '.join(DEMONSTRABLE)}, or drop it")  # fmt: skip
        if self.env != "treadmill" or self.hierarchical:
            where = "a hierarchical job's controller" if self.hierarchical else f"env {self.env!r}"
            raise ConfigError(field, f"demonstrators are treadmill reference policies, not for {where}; drop it")
        if name != "planner" and name not in REFERENCES:
            names = ", ".join(("planner", *REFERENCES))
            raise ConfigError(field, f"unknown reference policy {name!r}; choose one of: {names}")
        if self.algo_params.get("heads", 1) != 1:
            raise ConfigError(field, "a demonstration starts one Q-head; drop heads (or the demonstrator)")

    def _check_layout(self) -> None:
        """``encoder=entity`` reads the env's observation layout: refused here, before any process starts, when the
        env (with these parameters) has none."""
        from convoy.envs.layout import entity_layout
        from convoy.envs.registry import make_batched

        env = make_batched(self.env, 1, **self.env_params)
        env.close()
        try:
            entity_layout(env.spec)
        except ConfigError as exc:
            raise ConfigError("algo_params.encoder", str(exc).split(": ", 1)[-1]) from None

    def _check_seeds(self) -> None:
        """A population's seeds: distinct, in range, not beside a different ``seed``; one seed is a single run."""
        seeds = self.seeds
        if not seeds:
            return
        if len(set(seeds)) != len(seeds) or not all(0 <= s < 2**31 for s in seeds):
            raise ConfigError("seeds", f"expected distinct seeds in [0, 2^31), got {seeds}")
        if "seed" in self.model_fields_set and self.seed != seeds[0]:
            raise ConfigError("seeds", "give either seed (one run) or seeds (a population), not both")
        if self.hierarchical and self.algo == "dial" and len(seeds) > 1:
            raise ConfigError("seeds", "hierarchical DQN over DIAL trains one seed per process; drop seeds")
        object.__setattr__(self, "seed", seeds[0])
        if len(seeds) == 1:  # a population of one is the single run of its seed
            object.__setattr__(self, "seeds", [])

    @property
    def runs(self) -> int | None:
        """Runs of a population, or None for a single run."""
        return len(self.seeds) or None

    def run_seeds(self) -> list[int]:
        """The seed of every run: the population's, or the single run's."""
        return list(self.seeds) or [self.seed]

    def members(self) -> list[JobConfig]:
        """One job per run: the single run of its seed, which run k of the population reproduces."""
        return [self.model_copy(update={"seed": s, "seeds": []}) for s in self.run_seeds()]

    def write(self, path: str | Path) -> None:
        """The job as JSON at ``path``, defaults resolved: what ``--config`` and ``--resume`` read back (never the
        Zenoh password)."""
        saved = self.model_dump(mode="json", exclude={"runtime": {"zenoh": {"password"}}})
        Path(path).write_text(json.dumps(saved, indent=2) + "\n")

    def member_dirs(self, out_dir: str | Path) -> list[Path]:
        """Where each run writes: ``out_dir`` for a single run, ``out_dir/seed-N`` for each run of a population."""
        out = Path(out_dir)
        return [out / f"seed-{s}" for s in self.seeds] if self.seeds else [out]

    def agents_per_env(self) -> int:
        """Bodies simulated in one env (the treadmill's cars; the particle envs have at most 3): what ``num_envs``
        multiplies in an actor's memory."""
        return int(getattr(self.env_config(), "n_cars", 3))

    def algo_config(self) -> AlgoConfig:
        """The algorithm's resolved config (env defaults applied)."""
        return resolve_algo(self.algo, self.env, self.algo_params)

    def env_config(self) -> BaseModel:
        """The env's validated parameter model."""
        from convoy.envs.registry import env_entry

        return build_config(env_entry(self.env).config(), **self.env_params)


JOB_FIELDS: tuple[str, ...] = (
    "algo", "env", "preset", "steps", "num_envs", "seed", "hierarchical", "eval_episodes", "eval_messages",
    "eval_every", "log_every",
)  # fmt: skip
"""The scalar ``JobConfig`` fields a user picks per job: the flags of ``convoy train`` and ``convoy jobs submit``
(cli/train.py's JOB_FLAGS) and the job fields a sweep's grid may vary (api/models.py's GRID_FIELDS)."""


def _env_table() -> dict[str, Any]:
    from convoy.envs.registry import ENVS

    return ENVS


def job_config(**values: Any) -> JobConfig:
    """Build a JobConfig from plain values; any problem is a ConfigError naming the field."""
    return build_config(JobConfig, **values)
