"""Request and response bodies of the job service (OpenAPI at ``/docs``), shared with ``convoy jobs``.

A submitted job is validated by the same ``convoy.config.job_config`` as ``convoy train`` and the processes, so
a bad value gets the same message everywhere: the field, what was given and the allowed range. Bodies forbid
unknown fields (a typo is an error, not a silently ignored setting), take a count only as a JSON number (``true`` or
``"5"`` is not a count; ``5.0`` is 5, as JSON Schema says) and bound every count, so one request cannot
ask for a thousand processes.
"""

from __future__ import annotations

from typing import Any, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from convoy.config import (
    ALGORITHMS,
    JOB_FIELDS,
    MAX_POPULATION,
    ConfigError,
    JobConfig,
    MessageSource,
    Preset,
    RuntimeConfig,
    algo_name,
    job_config,
)

MAX_ACTORS = 64  # per job through the API (the runtime allows 256; a laptop's API should not)
ACTORS_DEFAULT: int = RuntimeConfig.model_fields["actors"].default
MAX_STEPS: int = next(m.le for m in JobConfig.model_fields["steps"].metadata if hasattr(m, "le"))


def job_field(name: str) -> Any:
    """``JobConfig``'s field ``name`` as a body field — its default, bounds and description — so that the REST
    body, ``convoy train`` and the processes share one definition."""
    info = JobConfig.model_fields[name]
    bounds = {k: getattr(m, k) for m in info.metadata for k in ("ge", "gt", "le", "lt", "max_length") if hasattr(m, k)}
    if info.default_factory is not None:
        return Field(default_factory=info.default_factory, description=info.description, **bounds)
    return Field(info.default, description=info.description, **bounds)


class JsonBody(BaseModel):
    """A request body: unknown fields refused, and a count only as a JSON number, a switch only as true/false
    (pydantic would take true for 1 and "5" for 5; the schema says integer, and ``5.0`` is one)."""

    model_config = ConfigDict(extra="forbid")

    @field_validator("*", mode="before")
    @classmethod
    def _json_types(cls, value: Any, info: ValidationInfo) -> Any:
        annotation = cls.model_fields[str(info.field_name)].annotation
        kinds = set(get_args(annotation)) or {annotation}
        if bool in kinds and not isinstance(value, bool):
            raise ValueError("must be true or false")
        if int in kinds and isinstance(value, bool | str):
            raise ValueError("must be a JSON number, not a boolean or a string")
        return value


class JobSubmit(JsonBody):
    """``POST /jobs``: what to train, on what, for how long, with how many actor processes."""

    algo: str = job_field("algo")
    env: str = job_field("env")
    preset: Preset | None = job_field("preset")
    env_params: dict[str, Any] = job_field("env_params")
    algo_params: dict[str, Any] = job_field("algo_params")
    hierarchical: bool = job_field("hierarchical")
    actors: int = Field(
        RuntimeConfig.model_fields["actors"].default, ge=1, le=MAX_ACTORS, description="Actor processes."
    )
    steps: int = job_field("steps")
    num_envs: int = job_field("num_envs")
    seed: int = job_field("seed")
    eval_episodes: int = job_field("eval_episodes")
    eval_messages: MessageSource = job_field("eval_messages")
    eval_every: int = job_field("eval_every")
    log_every: int = job_field("log_every")
    checkpoint_every: int = job_field("checkpoint_every")
    name: str | None = Field(
        None, pattern=r"^[A-Za-z0-9_.-]{1,32}$", description="Prefix of the job id (letters, digits, _ . -)."
    )
    runtime: dict[str, Any] = Field(
        default_factory=dict,
        description="Distributed runtime settings (RuntimeConfig's fields but actors, given above, and zenoh, which "
        'the service sets), e.g. {"actor_max_restarts": 500}.',
    )

    def job_config(self) -> JobConfig:
        """The validated job (ConfigError naming the field otherwise)."""
        for owned in ("actors", "zenoh"):
            if owned in self.runtime:
                fix = "give actors at the top level" if owned == "actors" else "the service chooses the transport"
                raise ConfigError(f"runtime.{owned}", f"not settable here; {fix}")
        values = self.model_dump(exclude={"actors", "name", "runtime"})
        return job_config(**values, runtime={**self.runtime, "actors": self.actors})


GRID_FIELDS = JOB_FIELDS  # the job fields a grid may vary: the CLI's job flags (convoy/config.py)
GRID_TABLES = ("env_params", "algo_params", "runtime")
MAX_SWEEP_JOBS = 1_000


class SweepSubmit(JsonBody):
    """``POST /sweeps``: one base job and a grid; every combination of the grid's values is one job.

    A grid axis is a job field (``algo``, ``seed``, ``steps``, …) or one parameter of its tables
    (``env_params.n_agents``, ``algo_params.lr``, ``runtime.publish_steps``). Jobs that differ only in ``seed``
    form one group of the summary."""

    name: str = Field(
        ..., pattern=r"^[A-Za-z0-9_.-]{1,32}$", description="Prefix of the sweep id (letters, digits, _ . -)."
    )
    base: dict[str, Any] = Field(
        default_factory=dict,
        description="The fields every job shares, as in POST /jobs (without name and actors), e.g. "
        '{"env": "referential", "steps": 20000}.',
    )
    grid: dict[str, list[Any]] = Field(
        ...,
        description='Axis → its values, e.g. {"algo": ["ma-mesn", "idqn"], "seed": [0, 1, 2, 3, 4]}.',
    )
    algos: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Hyper-parameters of one algorithm only, merged into base.algo_params for its jobs (a grid "
        'axis algo_params.NAME still wins), e.g. {"dial": {"replay": true}}.',
    )
    actors: int = Field(1, ge=1, le=MAX_ACTORS, description="Actor processes of each job.")
    threshold: float | None = Field(
        None, description="The return whose first crossing the summary times (env steps and seconds); none = no timing."
    )
    pack: int = Field(
        10,
        ge=1,
        le=MAX_POPULATION,
        description="Most seeds of one group trained together as one population job (one learner, one batched "
        "update; each seed still its own job of the sweep, with its own folder, metrics and summary), fewer where "
        "the service's resource limits allow fewer; 1 = one process group per job.",
    )
    exclude: list[dict[str, Any]] = Field(
        default_factory=list,
        description='Grid points not to run, each naming every axis, e.g. [{"algo": "idqn", "seed": 3}]: runs '
        "measured already (`convoy reproduce` leaves out those its ledger holds).",
    )

    @field_validator("grid")
    @classmethod
    def _axes(cls, grid: dict[str, list[Any]]) -> dict[str, list[Any]]:
        if not grid:
            raise ConfigError("grid", 'needs at least one axis, e.g. {"seed": [0, 1, 2]}')
        for axis, values in grid.items():
            table, _, key = axis.partition(".")
            if not (axis in GRID_FIELDS or (table in GRID_TABLES and key.isidentifier())):
                fields = ", ".join((*GRID_FIELDS, *(f"{t}.NAME" for t in GRID_TABLES)))
                raise ConfigError(f"grid.{axis}", f"is not a job field a sweep can vary; axes: {fields}")
            if not values:
                raise ConfigError(f"grid.{axis}", "has no values; give at least one")
            if len({repr(v) for v in values}) < len(values):
                raise ConfigError(f"grid.{axis}", f"repeats a value ({values!r}); each value once")
        size = 1
        for values in grid.values():
            size *= len(values)
        if size > MAX_SWEEP_JOBS:
            raise ConfigError("grid", f"makes {size:,} jobs; a sweep has at most {MAX_SWEEP_JOBS:,} — split it")
        return grid

    @field_validator("exclude")
    @classmethod
    def _exclude(cls, exclude: list[dict[str, Any]], info: ValidationInfo) -> list[dict[str, Any]]:
        grid: dict[str, list[Any]] = info.data.get("grid") or {}
        for i, point in enumerate(exclude):
            if set(point) != set(grid):
                raise ConfigError(
                    f"exclude[{i}]", f"names the axes {sorted(point)}; name every grid axis, {sorted(grid)}"
                )
            for axis, value in point.items():
                if repr(value) not in {repr(v) for v in grid[axis]}:
                    raise ConfigError(f"exclude[{i}].{axis}", f"{value!r} is not among grid.{axis}'s values")
        size = 1
        for values in grid.values():
            size *= len(values)
        if grid and len({repr(sorted(p.items())) for p in exclude}) >= size:
            raise ConfigError("exclude", "leaves no job of the grid to run; drop a point or submit nothing")
        return exclude

    @field_validator("algos")
    @classmethod
    def _algos(cls, algos: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        for name in algos:
            try:
                canonical = algo_name(name)
            except ConfigError as exc:
                raise ConfigError(f"algos.{name}", str(exc).split(": ", 1)[-1]) from None
            if canonical != name or name not in ALGORITHMS:
                raise ConfigError(f"algos.{name}", f"name the algorithm as the grid does: {canonical}")
        return algos

    @field_validator("base")
    @classmethod
    def _base(cls, base: dict[str, Any]) -> dict[str, Any]:
        for owned in ("name", "actors"):
            if owned in base:
                raise ConfigError(f"base.{owned}", "is the sweep's own: give it at the top of the sweep")
        return base


class JobPatch(JsonBody):
    """``PATCH /jobs/{id}``: scale the actor count of a job, live when it runs."""

    actors: int = Field(..., ge=1, le=MAX_ACTORS, description="Actor processes wanted.")


class JobResume(JsonBody):
    """``POST /jobs/{id}/resume``: continue from the last checkpoint, optionally with another actor count or a
    larger step budget."""

    actors: int | None = Field(None, ge=1, le=MAX_ACTORS, description="Actor processes (default: as before).")
    steps: int | None = Field(
        None, ge=1, le=JobConfig.model_fields["steps"].metadata[-1].le, description="New total env-step budget."
    )


class EvalRequest(JsonBody):
    """``POST /jobs/{id}/evaluate``: greedy episodes of a checkpoint of the job (``convoy eval``), in the
    background."""

    episodes: int = Field(100, ge=1, le=5_000, description="Greedy episodes.")
    messages: MessageSource = Field("sent", description="What the agents hear.")
    channel: str | None = Field(None, max_length=200, description="Lossy channel, e.g. drop=0.3,flip=0.01.")
    seed: int = Field(12345, ge=0, le=2**31 - 1, description="Seed of the evaluation envs.")
    checkpoint: str = Field(
        "checkpoint.pt",
        pattern=r"^[A-Za-z0-9_.-]{1,128}\.pt$",
        description="Which checkpoint: checkpoint.pt (the last) or best.pt (the best greedy point).",
    )


class EvaluationView(BaseModel):
    """An evaluation of a job's checkpoint, run in the background (``POST /jobs/{id}/evaluate``)."""

    id: str
    job: str
    state: str = Field(description="running, completed or failed.")
    request: dict[str, Any]
    created_at: float
    finished_at: float | None = None
    result: dict[str, Any] | None = Field(
        None, description="mean_return and its ci95 over the episodes, random_return beside them."
    )
    error: str | None = Field(None, description="Why it failed: the last line of its log.")


class EvaluationList(BaseModel):
    evaluations: list[EvaluationView]


class Progress(BaseModel):
    env_steps: int = 0
    fraction: float = 0.0
    updates: int | None = None
    return_: float | None = Field(
        None, alias="return", serialization_alias="return", description="ε-greedy training return of the last row."
    )
    eval_return: float | None = Field(None, description="The latest greedy evaluation (ε = 0, fixed seeds).")
    loss: float | None = None
    env_steps_per_s: float | None = None
    updates_per_s: float | None = None
    policy_lag: float | None = None
    demo_round: int | None = Field(
        None, description="DAgger rounds played so far by a job that starts from a demonstrator (at 0 env steps)."
    )
    demo_rounds: int | None = Field(None, description="Its DAgger rounds in all (algo_params.demo_rounds).")
    dropped: dict[str, dict[str, int]] = Field(
        default_factory=dict,
        description="Messages the job refused so far, by role (learner, actors, service) and reason: garbage, "
        "values no env can produce (action-range, non-finite, ...), overflow of a full queue (load, not an attack).",
    )

    model_config = ConfigDict(populate_by_name=True)


class FinalEvaluation(BaseModel):
    """The finished job's greedy evaluation (its ``summary.json``), beside the references on the same episodes."""

    eval_return: float | None = Field(None, description="Mean greedy return of the last policy.")
    eval_ci95: float | None = Field(None, description="Half-width of its 95 % confidence interval.")
    random_return: float | None = None
    references: dict[str, list[float | None]] = Field(
        default_factory=dict, description="Reference policy → [mean return, 95 % CI] (random, best constant, scripted)."
    )
    best_eval_return: float | None = Field(None, description="The best point of the greedy curve (best.pt).")
    best_eval_step: int | None = None
    wall_s: float | None = Field(None, description="Seconds the run took, resumes and its demonstration start in.")
    clone_s: float | None = Field(
        None, description="Of those, its demonstration start's (0: none; null: not known, resumed from an older run)."
    )


class JobView(BaseModel):
    """A job as ``GET /jobs/{id}`` shows it."""

    id: str
    state: str = Field(description="queued, starting, running, stopping, completed, stopped or failed.")
    algo: str
    env: str
    actors: int = Field(description="Actor processes requested.")
    actors_alive: int = Field(description="Actor processes holding a liveliness token now.")
    steps: int = Field(description="Env steps the job trains for.")
    progress: Progress
    created_at: float = Field(description="Unix time of the submission.")
    updated_at: float = Field(description="Unix time of the last state change or progress report.")
    error: str | None = Field(None, description="Why a failed job failed: the cause and what to do.")
    last_checkpoint: str | None = Field(None, description="Path of the newest checkpoint on the service's host.")
    queue_position: int | None = Field(None, description="Place in the queue of a queued job (1 = next).")
    config: dict[str, Any] = Field(description="The job's full configuration, defaults filled in.")
    final: FinalEvaluation | None = Field(None, description="The greedy evaluation of a completed job.")
    population: str | None = Field(
        None, description="A packed seed of a sweep: the population job that trains it (and stops, resumes, scales)."
    )
    members: list[str] = Field(
        default_factory=list, description="A population job: the sweep's seed jobs it trains, one run each."
    )


class JobList(BaseModel):
    jobs: list[JobView]


class MetricsPage(BaseModel):
    """Metric rows after ``since`` in step order; poll again with ``since = last_step`` for the next ones."""

    job: str
    rows: list[dict[str, Any]]
    last_step: int | None


class SweepMember(BaseModel):
    id: str
    point: dict[str, Any] = Field(description="The job's values of the grid's axes.")
    group: str = Field(description="Its group: the point without the seed.")
    state: str = Field(description="The job's state (deleted when it no longer exists).")
    env_steps: int = 0
    steps: int = 0
    demo_round: int | None = Field(
        None, description="DAgger rounds played so far while the job starts from a demonstrator (before its steps)."
    )
    demo_rounds: int | None = Field(None, description="Its DAgger rounds in all.")


class SweepView(BaseModel):
    """A sweep as ``GET /sweeps/{id}`` shows it: its jobs and how far they are."""

    id: str
    state: str = Field(
        description="running while a job is queued or runs; then completed (all), failed (any failed) or stopped."
    )
    created_at: float
    jobs: list[SweepMember]
    states: dict[str, int] = Field(description="How many of its jobs are in each state.")
    fraction: float = Field(description="Env steps done over env steps asked, all jobs together.")
    started_at: float | None = Field(None, description="Unix time its first job started.")
    ended_at: float | None = Field(None, description="Unix time its last job ended, once none is queued or running.")
    busy_s: float = Field(0.0, description="Seconds during which at least one of its jobs ran (pauses not counted).")
    spans: list[tuple[float, float]] = Field(
        default_factory=list,
        description="[start, end] Unix times of each job's latest run: busy_s is their union's length; sweeps that "
        "ran side by side are timed together by the union of all their spans.",
    )
    spec: dict[str, Any] = Field(description="The sweep as submitted.")


class SweepList(BaseModel):
    sweeps: list[SweepView]


class SweepSummary(BaseModel):
    """Per group: the mean greedy curve ± 95 % CI over seeds at common env steps, the final greedy return (mean with
    t-CI, ``iqm`` with a bootstrap CI), ``auc`` (area under each job's greedy curve per env step) and the time to
    the threshold (env steps and seconds of the seeds that reached it)."""

    id: str
    state: str
    threshold: float | None
    groups: list[dict[str, Any]]


class ErrorBody(BaseModel):
    """Every error: which field, what is wrong, what to do."""

    field: str
    problem: str
    fix: str
