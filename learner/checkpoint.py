"""Checkpoints: one file with the job, the env's shape, the algorithm's full state and the counters.

Written atomically (temporary file, fsync, rename), so a process killed mid-write leaves the previous checkpoint
intact. Loading rebuilds the algorithm from what the file says, so ``convoy eval`` and the learner's restart need
nothing else; every way a file can be wrong (missing, truncated, not ours, from a newer format) is a
``CheckpointError`` that says what to do.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from envs.batched import EnvSpec
from learner.agent import make_agent
from learner.algorithm import Algorithm, Progress
from learner.errors import CheckpointError
from protocol.config import JobConfig, job_config

FORMAT = 1
BEST_CHECKPOINT = "best.pt"  # beside checkpoint.pt: the policy of the best point of the greedy learning curve
__all__ = ["BEST_CHECKPOINT", "CheckpointError", "load_checkpoint", "read_checkpoint", "save_checkpoint"]


def save_checkpoint(path: str | Path, algo: Algorithm, job: JobConfig, counters: dict[str, Any]) -> Path:
    """Write ``algo``'s state atomically to ``path`` (parents created)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "kind": "convoy-checkpoint",
        "algo": algo.name,
        "job": job.model_dump(mode="json"),
        "spec": asdict(algo.spec),
        "state": algo.state_dict(),
        "counters": dict(counters),
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(payload, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The raw payload of a checkpoint file, validated for kind and format."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint {path}: no such file; train one with `convoy train` (it writes checkpoint.pt)"
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # truncated, not a torch file, …
        raise CheckpointError(
            f"checkpoint {path}: cannot be read ({type(exc).__name__}); it is corrupt or not a Convoy checkpoint — "
            "use an earlier checkpoint or retrain"
        ) from None
    if not isinstance(payload, dict) or payload.get("kind") != "convoy-checkpoint":
        raise CheckpointError(f"checkpoint {path}: not a Convoy checkpoint (no 'kind' marker)")
    if payload.get("format") != FORMAT:
        raise CheckpointError(
            f"checkpoint {path}: format {payload.get('format')!r}, this Convoy reads format {FORMAT}; "
            "use the Convoy version that wrote it"
        )
    return payload


def load_checkpoint(path: str | Path, device: str = "auto") -> tuple[Algorithm, JobConfig, dict[str, Any]]:
    """Rebuild the algorithm from a checkpoint: (algorithm, job, counters)."""
    payload = read_checkpoint(path)
    try:
        job = job_config(**payload["job"])
        spec_d = payload["spec"]
        spec = EnvSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in spec_d.items()})
        algo = make_agent(job, spec, device=device)
        algo.load_state_dict(payload["state"])
        counters = payload.get("counters", {})
        # a loaded policy acts as it did when saved (fingerprints, schedules), not as at step 0
        algo.progress = Progress(int(counters.get("env_steps", 0)), int(counters.get("episodes", 0)), job.steps)
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path}: does not match this Convoy's networks ({exc}); retrain") from None
    return algo, job, payload.get("counters", {})
