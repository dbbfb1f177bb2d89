"""Checkpoints: one file with the job, the env's shape, the algorithm's full state and the counters.

Written atomically (temporary file, fsync, rename), so a process killed mid-write leaves the previous checkpoint
intact. Read with ``torch.load(weights_only=True)``: a file holds tensors and plain data (dicts, lists, numbers,
strings) only, so a hostile file given as a checkpoint or a CoDBC teacher cannot run code; it is refused. Loading
rebuilds the algorithm from what the file says, so ``convoy eval`` and the learner's restart need nothing else;
every way a file can be wrong (missing, truncated, not ours, from a newer format, holding code) is a
``CheckpointError`` that says what to do.
"""

from __future__ import annotations

import logging
import os
import pickle
import tempfile
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from convoy.algos.agent import make_agent
from convoy.algos.algorithm import Agent, Progress
from convoy.algos.errors import CheckpointError
from convoy.algos.replay import JointReplay
from convoy.config import JobConfig, job_config
from convoy.envs.batched import EnvSpec

log = logging.getLogger(__name__)

FORMAT = 1
PREVIOUS_CHECKPOINT = "checkpoint.previous.pt"  # a population's run keeps its checkpoint before the last
BEST_CHECKPOINT = "best.pt"  # beside checkpoint.pt: the policy of the best point of the greedy learning curve
REPLAY_FILE = "replay.npz"  # beside checkpoint.pt: the replay buffers at its env step, when small enough to keep
__all__ = [
    "BEST_CHECKPOINT",
    "PREVIOUS_CHECKPOINT",
    "REPLAY_FILE",
    "CheckpointError",
    "drop_replay",
    "load_checkpoint",
    "load_replay",
    "read_checkpoint",
    "replay_buffers",
    "save_checkpoint",
    "save_replay",
]


def save_checkpoint(path: str | Path, algo: Agent, job: JobConfig, counters: dict[str, Any]) -> Path:
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
    _write_atomically(path, lambda fh: torch.save(payload, fh))
    return path


def _write_atomically(path: Path, write: Callable[[IO[bytes]], None]) -> None:
    """``write`` into a temporary file beside ``path``, fsync, rename: a process killed mid-write leaves the
    previous file intact."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The raw payload of a checkpoint file, validated for kind and format."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint {path}: no such file; train one with `convoy train` (it writes checkpoint.pt)"
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)  # never runs code from the file
    except pickle.UnpicklingError as exc:
        if "unsupported global" not in str(exc).lower():  # garbage, not an object to build
            raise CheckpointError(
                f"checkpoint {path}: cannot be read (not a pickle torch can read); it is corrupt or not a Convoy "
                "checkpoint — use an earlier checkpoint or retrain"
            ) from None
        raise CheckpointError(
            f"checkpoint {path}: refused — it holds Python objects, not only tensors and plain data, and loading it "
            "could run code. Convoy's checkpoints never do (every Convoy checkpoint loads); take this file only if "
            "you trust it, and convert it yourself"
        ) from None
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


def load_checkpoint(path: str | Path, device: str = "auto") -> tuple[Agent, JobConfig, dict[str, Any]]:
    """Rebuild the algorithm from a checkpoint: (algorithm, job, counters)."""
    payload = read_checkpoint(path)
    try:
        job = job_config(**payload["job"])
        spec = EnvSpec.from_dict(payload["spec"])
        algo = make_agent(job, spec, device=device)
        algo.load_state_dict(payload["state"])
        counters = payload.get("counters", {})
        # a loaded policy acts as it did when saved (fingerprints, schedules), not as at step 0
        algo.progress = Progress(int(counters.get("env_steps", 0)), int(counters.get("episodes", 0)), job.steps)
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path}: does not match this Convoy's networks ({exc}); retrain") from None
    return algo, job, payload.get("counters", {})


# ------------------------------------------------------------------------------------------------------ replay
def replay_buffers(algo: Any) -> dict[str, JointReplay]:
    """Every replay buffer of an algorithm by name (a hierarchical agent has one per level)."""
    if hasattr(algo, "controller") and hasattr(algo, "meta"):
        return {
            f"{level}.{k}": v
            for level in ("controller", "meta")
            for k, v in replay_buffers(getattr(algo, level)).items()
        }
    buffers = {name: getattr(algo, name, None) for name in ("replay", "demos")}  # demos: ``demo_margin``'s
    return {name: buf for name, buf in buffers.items() if isinstance(buf, JointReplay)}


PRIORITIES = ("priority", "max_priority")  # prioritized replay's arrays in a replay file, beside its rows


def save_replay(
    path: str | Path, algo: Any, env_steps: int, max_bytes: int, say: Callable[[str], None] | None = None
) -> int:
    """Write ``algo``'s replay (filled rows only) atomically to ``path`` when it holds at most ``max_bytes``; the
    bytes written, or 0 when it is larger (the file is then removed: a stale one must not be loaded later, and
    ``say`` hears why: a resume from that checkpoint starts with an empty buffer).

    Why: a restarted learner with an empty buffer trains its high replay ratio on a few thousand fresh rows and its
    return collapses (~40 → ~5) until the buffer refills; with the buffer back it carries on."""
    path = Path(path)
    buffers = replay_buffers(algo)
    size = sum(len(b) * (b.nbytes // max(b.allocated, 1)) for b in buffers.values())  # filled rows × row bytes
    if not buffers or size > max_bytes:
        path.unlink(missing_ok=True)
        if buffers and say is not None:
            say(f"replay not saved with this checkpoint: its {size / 2**20:,.0f} MB are over "
                f"runtime.replay_checkpoint_mb = {max_bytes >> 20:,}, so a resume from it starts with an empty "
                "buffer; raise it with --runtime replay_checkpoint_mb=N")  # fmt: skip
        return 0
    arrays: dict[str, np.ndarray] = {"env_steps": np.asarray(env_steps)}
    for name, buf in buffers.items():
        state = buf.state_dict()
        arrays[f"{name}/next"] = np.asarray(state["next"])
        arrays[f"{name}/size"] = np.asarray(state["size"])
        arrays.update({f"{name}/{k}": state[k] for k in PRIORITIES if k in state})
        arrays.update({f"{name}/data/{k}": v for k, v in state["data"].items()})
    if path.is_file():  # the checkpoint on disk still points at this one until the next checkpoint is written
        path.replace(previous_replay(path))
    # allow_pickle named (numpy's default) so that the checker does not match **arrays to it
    _write_atomically(path, lambda fh: np.savez(fh, allow_pickle=True, **arrays))
    return size


def drop_replay(path: str | Path) -> None:
    """Delete a replay file and the one of the checkpoint before (a completed run needs neither)."""
    Path(path).unlink(missing_ok=True)
    previous_replay(Path(path)).unlink(missing_ok=True)


def previous_replay(path: Path) -> Path:
    """Where the replay of the checkpoint before lies: a learner killed between writing the new replay and the new
    checkpoint resumes from the old checkpoint, whose replay this is."""
    return path.with_name(f"{path.stem}.previous{path.suffix}")


def _replay_step(path: Path) -> int | None:
    """The env step a replay file was saved at; None when there is none or it cannot be read (said, when it is
    there)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as data:
            return int(data["env_steps"])
    except (OSError, KeyError, ValueError) as exc:
        log.warning("replay %s unusable (%s: %s); refilling from actors", path, type(exc).__name__, exc)
        return None


def load_replay(path: str | Path, algo: Any, env_steps: int) -> int:
    """Fill ``algo``'s replay from ``path`` if it was saved at ``env_steps`` (the checkpoint's step); rows loaded.
    A missing, unreadable or mismatched file loads nothing: the learner then refills its buffer from actors."""
    matching = [p for p in (Path(path), previous_replay(Path(path))) if _replay_step(p) == env_steps]
    if not matching:
        return 0
    path = matching[0]
    try:
        with np.load(path) as data:
            buffers = replay_buffers(algo)
            states = {
                name: {
                    "next": data[f"{name}/next"],
                    **({"size": data[f"{name}/size"]} if f"{name}/size" in data.files else {}),
                    **{k: data[f"{name}/{k}"] for k in PRIORITIES if f"{name}/{k}" in data.files},
                    "data": {k.split("/", 2)[2]: data[k] for k in data.files if k.startswith(f"{name}/data/")},
                }
                for name in buffers
            }
        for name, buf in buffers.items():
            buf.load_state_dict(states[name])
    except (OSError, KeyError, ValueError) as exc:
        log.warning("replay %s unusable (%s: %s); refilling from actors", path, type(exc).__name__, exc)
        for buf in replay_buffers(algo).values():
            buf.load_state_dict({"data": {}, "next": 0})
        return 0
    return sum(len(b) for b in replay_buffers(algo).values())
