"""The files a job's config names, checked before anything runs: a job that names a file it cannot use is refused
where it is given (``convoy train``, ``POST /jobs``), naming the field, instead of a process that dies at its first
step. Imports nothing heavy until a job names a file (the job service calls it on every submission)."""

from __future__ import annotations

from convoy.config import JobConfig
from convoy.validation import ConfigError


def check_inputs(job: JobConfig) -> None:
    """The files a job's config names exist, load and fit its env — today a CoDBC teacher checkpoint: a ConfigError
    naming the field (``algo_params.teacher``) before any folder is made or process started, not a process that
    dies at its first step. Paths are read as the job's processes will read them (relative to this folder)."""
    teacher = getattr(job.algo_config(), "teacher", None) if job.algo == "codbc" else None
    if not teacher:
        return
    from convoy.algos.codbc import load_teacher
    from convoy.envs import make_batched

    spec = None
    if not job.hierarchical:  # a hierarchical controller sees its goal too: its own check compares the shapes
        env = make_batched(job.env, 1, **job.env_params)
        spec = env.spec
        env.close()
    try:
        load_teacher(str(teacher), spec, device="cpu")
    except ConfigError as exc:
        raise ConfigError(f"algo_params.{exc.field}", str(exc).split(": ", 1)[-1]) from None
