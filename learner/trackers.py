"""Experiment trackers: every metric row and the final summary to TensorBoard (always) and to the trackers a job asks
for (``JobConfig.loggers``: ``wandb``, ``mlflow``), beside the run's own JSONL/CSV.

TensorBoard's event files go to ``RUN/tb/``: ``tensorboard --logdir runs`` shows every run there. Names are grouped
(``eval/return`` with its 95 % interval as ``eval/lower``/``eval/upper`` and a margin chart of the three,
``train/…``, ``speed/…``, ``transport/…``); the job's config goes in as hyper-parameters with the final and best
greedy returns as their metrics. A resumed run drops the events past its checkpoint (``purge_step``), as the
metric files do. W&B and MLflow get the same rows and summary; each is an optional extra (``pip install
'convoy[wandb]'``) imported only when asked for, and each works as installed, with no account, server or
environment variable: MLflow logs to a file store in ``RUN/mlruns`` unless ``MLFLOW_TRACKING_URI`` names another
store, and W&B runs offline in ``RUN/wandb`` unless it has an API key (``wandb login``) or ``WANDB_MODE`` says
otherwise. ``check_loggers`` tries the job's trackers before a run makes its folder, so a tracker that cannot work
is one line that says what to set, and no run is left half-made.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from collections.abc import Callable, Sequence
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
    """A W&B run named after the run's folder, in ``RUN/wandb``: online with an API key (``wandb login`` or
    ``WANDB_API_KEY``), else offline (``wandb sync RUN/wandb/offline-run-*`` uploads it later); ``WANDB_MODE``
    decides when set."""

    def __init__(self, out_dir: Path, config: dict[str, Any]) -> None:
        wandb = _optional("wandb")
        mode = wandb_mode()
        self.run = wandb.init(dir=str(out_dir), name=out_dir.name, config=config, mode=mode, reinit=_reinit(wandb))

    def row(self, step: int, values: dict[str, float]) -> None:
        self.run.log(values, step=step)

    def summary(self, config: dict[str, Any], final: dict[str, float]) -> None:
        self.run.summary.update(final)

    def close(self) -> None:
        self.run.finish()


def wandb_mode() -> str:
    """``WANDB_MODE`` when set; else online when W&B has an API key for its host, offline when not (W&B itself
    would ask for a key, or fail without a terminal)."""
    return os.environ.get("WANDB_MODE") or ("online" if _wandb_key() else "offline")


def _wandb_key() -> bool:
    """Whether W&B has an API key: ``WANDB_API_KEY``, or a ``.netrc`` entry for its host (``wandb login``)."""
    import netrc
    from urllib.parse import urlparse

    if os.environ.get("WANDB_API_KEY"):
        return True
    host = urlparse(os.environ.get("WANDB_BASE_URL") or "https://api.wandb.ai").hostname or "api.wandb.ai"
    path = os.environ.get("NETRC") or os.path.join(os.path.expanduser("~"), ".netrc")
    try:
        entry = netrc.netrc(path).authenticators(host)
    except (OSError, netrc.NetrcParseError):
        return False
    return bool(entry and entry[2])


def _reinit(wandb: Any) -> Any:
    """Runs side by side in one process (a population's seeds): each its own W&B run, none finishing another."""
    try:
        version = tuple(int(p) for p in str(wandb.__version__).split(".")[:3])
    except ValueError:
        return True
    return "create_new" if version >= (0, 19, 10) else True


class MLflow:
    """An MLflow run in ``MLFLOW_TRACKING_URI`` when set, else in a file store in the run's folder (``RUN/mlruns``:
    ``mlflow ui --backend-store-uri RUN/mlruns``), under ``MLFLOW_EXPERIMENT_NAME`` (default ``Default``). Through
    its own client: runs side by side in one process (a population's seeds) never share MLflow's active run."""

    def __init__(self, out_dir: Path, config: dict[str, Any]) -> None:
        _optional("mlflow")
        from mlflow.entities import Param
        from mlflow.tracking import MlflowClient

        self.client = MlflowClient(tracking_uri=mlflow_uri(out_dir))
        name = os.environ.get("MLFLOW_EXPERIMENT_NAME") or "Default"
        found = self.client.get_experiment_by_name(name)
        experiment = found.experiment_id if found is not None else self.client.create_experiment(name)
        self.run_id = self.client.create_run(experiment, run_name=out_dir.name).info.run_id
        params = [Param(k, str(v)[:500]) for k, v in flat(config).items()]
        for at in range(0, len(params), 100):  # MLflow takes at most 100 params a batch
            self.client.log_batch(self.run_id, params=params[at : at + 100])

    def _log(self, values: dict[str, float], step: int) -> None:
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        metrics = [Metric(k, v, now, step) for k, v in values.items()]
        for at in range(0, len(metrics), 1000):
            self.client.log_batch(self.run_id, metrics=metrics[at : at + 1000])

    def row(self, step: int, values: dict[str, float]) -> None:
        self._log({k.replace("/", "."): v for k, v in values.items()}, step)

    def summary(self, config: dict[str, Any], final: dict[str, float]) -> None:
        self._log({f"final.{k}": v for k, v in final.items()}, 0)

    def close(self) -> None:
        self.client.set_terminated(self.run_id)


MLRUNS_DIR = "mlruns"


def mlflow_uri(out_dir: Path) -> str:
    """``MLFLOW_TRACKING_URI`` when set; else a file store in ``out_dir/mlruns``, allowed in this process (MLflow 3
    refuses file stores unless ``MLFLOW_ALLOW_FILE_STORE`` is set, and mlflow-skinny cannot open the database it
    would default to)."""
    if uri := os.environ.get("MLFLOW_TRACKING_URI"):
        return uri
    os.environ.setdefault("MLFLOW_ALLOW_FILE_STORE", "true")
    return (out_dir.resolve() / MLRUNS_DIR).as_uri()


def check_loggers(loggers: Sequence[str]) -> None:
    """Try the trackers a job asks for before its run makes a folder: a ConfigError naming ``loggers`` and what to
    set when one cannot work here (not installed, a store MLflow cannot open, W&B online without a key)."""
    for name in loggers:
        _optional(name)
        if name == "mlflow":
            _check_mlflow()
        elif name == "wandb" and wandb_mode() == "online" and not _wandb_key():
            raise ConfigError("loggers", "wandb: WANDB_MODE=online but W&B has no API key; run `wandb login` (or set "
                              "WANDB_API_KEY), or unset WANDB_MODE to log offline into RUN/wandb")  # fmt: skip


def _check_mlflow() -> None:
    from mlflow.tracking import MlflowClient

    given = os.environ.get("MLFLOW_TRACKING_URI")
    with tempfile.TemporaryDirectory(prefix="convoy-mlflow-") as scratch:
        uri = mlflow_uri(Path(scratch))  # the store a run would use (in a scratch folder when it is the run's own)
        try:
            client = MlflowClient(tracking_uri=uri)  # opens the store (a server is not asked: it may be offline now)
            if not given:
                client.search_experiments(max_results=1)
        except Exception as exc:
            why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
            if not given:
                if "MLFLOW_ALLOW_FILE_STORE" in str(exc):
                    why = f"MLFLOW_ALLOW_FILE_STORE={os.environ.get('MLFLOW_ALLOW_FILE_STORE')} forbids it"
                raise ConfigError("loggers", f"mlflow cannot open a file store in RUN/mlruns ({why}); unset "
                                  "MLFLOW_ALLOW_FILE_STORE, or set MLFLOW_TRACKING_URI to a tracking server or "
                                  "database") from None  # fmt: skip
            if "MLFLOW_ALLOW_FILE_STORE" in str(exc):
                why = "MLflow refuses file stores unless MLFLOW_ALLOW_FILE_STORE=true"
                fix = "set MLFLOW_ALLOW_FILE_STORE=true, or unset MLFLOW_TRACKING_URI to log into RUN/mlruns"
            elif "unsupported URI" in str(exc) and not uri.startswith(("http", "databricks")):
                why = "this MLflow cannot open that kind of store (mlflow-skinny has no database stores)"
                fix = "pip install mlflow, or unset MLFLOW_TRACKING_URI to log into RUN/mlruns"
            else:
                fix = "fix it, or unset it to log into RUN/mlruns"
            shown = re.sub(r"//[^/@]*@", "//", uri)  # never a password in an error line
            raise ConfigError("loggers", f"mlflow cannot use MLFLOW_TRACKING_URI={shown} ({why}); {fix}") from None


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
        for name in loggers:
            try:
                self.all.append(kinds[name](out, config))
            except Exception as exc:  # what check_loggers could not foresee (a server that refuses): one line
                self.close()
                if isinstance(exc, ConfigError):
                    raise
                why = (str(exc).strip().splitlines() or [""])[0][:300]
                raise ConfigError("loggers", f"{name} could not start ({type(exc).__name__}: {why}); fix its "
                                  f"settings or drop --logger {name}") from None  # fmt: skip

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
