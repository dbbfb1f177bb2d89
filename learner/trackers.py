"""Experiment trackers: every metric row and the final summary to TensorBoard (always) and to the trackers a job asks
for (``JobConfig.loggers``: ``wandb``, ``mlflow``), beside the run's own JSONL/CSV.

TensorBoard's event files go to ``RUN/tb/``: ``tensorboard --logdir runs`` shows every run there. Names are grouped
(``eval/return`` with its 95 % interval as ``eval/lower``/``eval/upper`` and a margin chart of the three,
``train/…``, ``speed/…``, ``transport/…``); the job's config goes in as hyper-parameters with the final and best
greedy returns as their metrics. A resumed run drops the events past its checkpoint (``purge_step``), as the
metric files do. W&B and MLflow get the same rows and summary; each is an optional extra (``pip install
'convoy[wandb]'``) imported only when asked for.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from convoy.config import ConfigError

TB_DIR = "tb"
SPEED = ("env_steps_per_s", "updates_per_s", "actor_env_steps_per_s", "wall_s")
TRANSPORT = ("policy_lag", "dropped", "chunks", "actors_alive")


def metric_name(key: str) -> str:
    """A row's column as a grouped tracker name: ``eval_return`` → ``eval/return``, ``loss`` → ``train/loss``."""
    if key.startswith("eval_"):
        return "eval/" + key[len("eval_") :]
    if key in SPEED:
        return "speed/" + key
    if key in TRANSPORT or key.startswith("dropped_"):
        return "transport/" + key
    return "train/" + key


def scalars(row: dict[str, Any]) -> dict[str, float]:
    """The row's finite numbers under their tracker names, the greedy return's interval bounds added."""
    out = {
        metric_name(k): float(v)
        for k, v in row.items()
        if k != "env_steps" and isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
    }
    if "eval/return" in out and "eval/ci95" in out:
        out["eval/lower"] = out["eval/return"] - out["eval/ci95"]
        out["eval/upper"] = out["eval/return"] + out["eval/ci95"]
    return out


def flat(config: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested config as ``a.b`` keys with scalar values (lists as strings): what hyper-parameter tables take."""
    out: dict[str, Any] = {}
    for k, v in config.items():
        if isinstance(v, dict):
            out.update(flat(v, f"{prefix}{k}."))
        elif isinstance(v, bool | int | float | str) or v is None:
            out[f"{prefix}{k}"] = "none" if v is None else v
        else:
            out[f"{prefix}{k}"] = str(v)
    return out


class Tracker(Protocol):
    def row(self, step: int, values: dict[str, float]) -> None: ...
    def summary(self, config: dict[str, Any], final: dict[str, float]) -> None: ...
    def close(self) -> None: ...


class TensorBoard:
    """``RUN/tb/``: scalars per row, a margin chart of the greedy return, the config as hyper-parameters."""

    def __init__(self, out_dir: Path, resume_at: int | None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.dir = out_dir / TB_DIR
        purge = None if resume_at is None else resume_at + 1  # events past the checkpoint are being redone
        self.writer = SummaryWriter(log_dir=str(self.dir), purge_step=purge)
        layout = {"greedy evaluation": {"return (95 % CI)": ["Margin", ["eval/return", "eval/lower", "eval/upper"]]}}
        self.writer.add_custom_scalars(layout)

    def row(self, step: int, values: dict[str, float]) -> None:
        for name, value in values.items():
            self.writer.add_scalar(name, value, global_step=step)
        self.writer.flush()

    def summary(self, config: dict[str, Any], final: dict[str, float]) -> None:
        self.writer.add_hparams(flat(config), {f"hparam/{k}": v for k, v in final.items()}, run_name=".")
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


class WandB:
    """A W&B run named after the run's folder (``WANDB_MODE=offline`` keeps it on disk)."""

    def __init__(self, out_dir: Path, config: dict[str, Any]) -> None:
        wandb = _optional("wandb")
        self.run = wandb.init(dir=str(out_dir), name=out_dir.name, config=config, reinit=True)

    def row(self, step: int, values: dict[str, float]) -> None:
        self.run.log(values, step=step)

    def summary(self, config: dict[str, Any], final: dict[str, float]) -> None:
        self.run.summary.update(final)

    def close(self) -> None:
        self.run.finish()


class MLflow:
    """An MLflow run in the tracking URI MLflow is set to (``MLFLOW_TRACKING_URI``; by default ``./mlruns``)."""

    def __init__(self, out_dir: Path, config: dict[str, Any]) -> None:
        self.mlflow = _optional("mlflow")
        self.run = self.mlflow.start_run(run_name=out_dir.name)
        self.mlflow.log_params({k: str(v)[:500] for k, v in flat(config).items()})

    def row(self, step: int, values: dict[str, float]) -> None:
        self.mlflow.log_metrics({k.replace("/", "."): v for k, v in values.items()}, step=step)

    def summary(self, config: dict[str, Any], final: dict[str, float]) -> None:
        self.mlflow.log_metrics({f"final.{k}": v for k, v in final.items()})

    def close(self) -> None:
        self.mlflow.end_run()


def _optional(name: str) -> Any:
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError:
        raise ConfigError("loggers", f"{name} is not installed: pip install 'convoy[{name}]', or drop it") from None


class Trackers:
    """TensorBoard and the job's other trackers, fed the same rows and summary."""

    def __init__(
        self, out_dir: str | Path, config: dict[str, Any], loggers: tuple[str, ...] = (), resume_at: int | None = None
    ) -> None:
        out = Path(out_dir)
        self.config = config
        self.all: list[Tracker] = [TensorBoard(out, resume_at)]
        kinds: dict[str, Callable[[Path, dict[str, Any]], Tracker]] = {"wandb": WandB, "mlflow": MLflow}
        self.all += [kinds[name](out, config) for name in loggers]

    def row(self, row: dict[str, Any]) -> None:
        values = scalars(row)
        for tracker in self.all:
            tracker.row(int(row["env_steps"]), values)

    def summary(self, summary: dict[str, Any]) -> None:
        keys = ("eval_return", "eval_ci95", "best_eval_return", "random_return")
        final = {k: float(summary[k]) for k in keys if isinstance(summary.get(k), int | float)}
        for tracker in self.all:
            tracker.summary(self.config, {k: v for k, v in final.items() if math.isfinite(v)})

    def close(self) -> None:
        for tracker in self.all:
            tracker.close()
