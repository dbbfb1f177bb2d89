"""Evaluations of a job's checkpoint in the background: ``POST /jobs/{id}/evaluate`` starts ``convoy eval`` as its
own process and answers at once; ``GET /jobs/{id}/evaluations/{eid}`` follows it.

Why a process: thousands of greedy episodes take minutes of CPU; inside the API process they would stall every
request. Each evaluation lives in the job's folder (``evaluations/EID/``: ``request.json`` with the process id,
``eval.log``, and ``result.json`` once done), so its state survives a restart of the service: a result means
completed, a live process running, neither failed (with the log's last line as the reason).
"""

from __future__ import annotations

import json
import secrets
import subprocess
import time
from pathlib import Path
from typing import Any

from convoy.api.lifecycle import StoreError, UnknownEvaluation
from convoy.api.models import EvalRequest
from convoy.api.remedy import ConfigRefusal, Fix, Step
from convoy.services.procs import pid_alive

MAX_RUNNING = 2  # evaluations at once, service-wide: each takes a core
_CHILDREN: dict[int, subprocess.Popen] = {}  # this process's running evaluations, until reaped


def reap() -> None:
    """Collect the exit of every evaluation this process started that has ended: an unreaped child stays a zombie,
    and a zombie's pid looks alive (a failed evaluation would show as running for ever)."""
    for pid, proc in list(_CHILDREN.items()):
        if proc.poll() is not None:
            del _CHILDREN[pid]


def view(folder: Path, job_id: str) -> dict[str, Any]:
    """One evaluation as the API shows it, from its folder."""
    reap()
    request = json.loads((folder / "request.json").read_text())
    out: dict[str, Any] = {
        "id": folder.name,
        "job": job_id,
        "request": request["request"],
        "created_at": request["created_at"],
        "finished_at": None,
        "result": None,
        "error": None,
    }
    result = folder / "result.json"
    if result.is_file():
        out.update(state="completed", result=json.loads(result.read_text()), finished_at=result.stat().st_mtime)
        out["result"].pop("returns", None)  # every episode's return stays in the file
    elif pid_alive(int(request["pid"])):
        out["state"] = "running"
    else:
        lines = [ln for ln in (folder / "eval.log").read_text(errors="replace").splitlines() if ln.strip()]
        out.update(state="failed", error=(lines[-1] if lines else "ended without output")[-300:])
    return out


def listing(job_dir: Path, job_id: str) -> list[dict[str, Any]]:
    """Every evaluation of the job, oldest first."""
    root = job_dir / "evaluations"
    folders = [f for f in root.iterdir() if (f / "request.json").is_file()] if root.is_dir() else []
    views = [view(f, job_id) for f in folders]
    return sorted(views, key=lambda v: v["created_at"])


def start(job_dir: Path, job_id: str, request: EvalRequest, running_elsewhere: int, python: str) -> dict[str, Any]:
    """Start ``convoy eval`` on the job's checkpoint; a ConfigError when there is none or the request is bad."""
    checkpoint = job_dir / request.checkpoint
    if not checkpoint.is_file():
        raise ConfigRefusal(
            "checkpoint",
            f"job {job_id!r} has no {request.checkpoint} yet; it writes one every checkpoint_every env steps",
            Fix("evaluate one it has: {}", Step("GET /jobs/{id}/checkpoints", job_id)),
        )
    if request.channel:
        from convoy.analysis.evaluation import parse_channel

        parse_channel(request.channel)
    if running_elsewhere >= MAX_RUNNING:
        raise StoreError(f"{running_elsewhere} evaluations are running; this service runs {MAX_RUNNING} at once",
                         Fix("wait for one to end: {}", Step("GET /jobs/{id}/evaluations", job_id)))  # fmt: skip
    folder = job_dir / "evaluations" / secrets.token_hex(3)
    folder.mkdir(parents=True)
    cmd = [python, "-m", "convoy.cli", "eval", str(checkpoint), "--episodes", str(request.episodes),
           "--messages", request.messages, "--seed", str(request.seed), "--json", str(folder / "result.json"),
           "--device", "cpu"] + (["--channel", request.channel] if request.channel else [])  # fmt: skip
    with open(folder / "eval.log", "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    _CHILDREN[proc.pid] = proc
    record = {"request": request.model_dump(mode="json"), "pid": proc.pid, "created_at": time.time()}
    (folder / "request.json").write_text(json.dumps(record, indent=2))
    return view(folder, job_id) | {"state": "running"}


def find(job_dir: Path, job_id: str, eval_id: str) -> dict[str, Any]:
    folder = job_dir / "evaluations" / eval_id
    if not (folder / "request.json").is_file():
        raise UnknownEvaluation(f"job {job_id!r} has no evaluation {eval_id!r}")
    return view(folder, job_id)
