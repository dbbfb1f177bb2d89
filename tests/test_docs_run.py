"""Every console command of README.md and docs/ runs as written, at a small budget, in a scratch directory.

``test_docs_commands`` checks that they parse; here they execute: the ``convoy`` commands in this process (their
``--steps``, episodes and samples shrunk, ``--actors`` at most 2, ``--seeds`` the first two), the benchmark scripts
that keep to themselves in it too (``IN_PROCESS``), the others and the ``make`` targets as processes, the service
sessions (README and docs/service.md: ``convoy serve``, then the ``curl``, ``convoy jobs`` and ``convoy sweep`` lines
in their order, with the ids the service really gave in place of the docs' examples), the many-hosts topology of
docs/training.md on 127.0.0.1, and ``tensorboard`` on a run. A command the docs show refused must fail with the error
they show; every other must succeed. Runs a command needs (``runs/demo``, ``runs/glimpse`` …) come from the
documented command that writes them, once per test session (``ensure``). ``make test`` is the command that runs this.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from unittest import mock

import httpx
import pytest
from filelock import FileLock

from convoy.config import DEMO_PRESETS
from convoy.protocol.session import free_port
from tests.doc_output import compare, output_blocks
from tests.service_fixture import Service
from tests.test_docs_commands import ASSIGNMENT, COMMANDS, OUTPUT, expand

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SERVICE = ("convoy serve", "convoy jobs", "convoy sweep", "curl ", "export ", "make serve")
OWN_TESTS = (*SERVICE, "convoy router", "convoy host", "tensorboard", "make ")
GENERIC = [(w, c) for w, c in COMMANDS if not c.startswith(OWN_TESTS) and not ASSIGNMENT.match(c)]
# every second command runs in tests/test_docs_run_second_half.py: this file would otherwise hold ~70 % of the suite's
# time on one worker (``--dist loadfile`` keeps a file on one worker, so its fixtures are made once)
FIRST_HALF, SECOND_HALF = GENERIC[0::2], GENERIC[1::2]


BLOCKS = {b.where: b for b in output_blocks()}  # what the docs show each command print, by its line
# a session's outputs at the small budget: compared by template, with only the counts no budget changes; a table's
# rows (its jobs, their states and figures) and a watch's progress lines are one session's, left out
SESSION = [(r"@ jobs in # groups|# jobs in @ groups|@ completed, watched|queued #@|retry: @", 0.0), (r"@", None)]
SESSION_ONLY = re.compile(r"^\s*│|^\S+ running: ")
# at the docs' budget: the counts the budget fixes exactly; a referential success rate (a sweep's, an evaluation's)
# within 0.3 and a treadmill return within 8, for runs with actor processes differ from run to run (the actors'
# timing decides which transitions the learner has when); what timing decides not at all (the env steps a seed
# took to reach the threshold, the progress lines of a watch, the rows of a live job's metrics and the job list)
FULL = [(r"reached; @|reached; # ± @", None),
        (r"@ jobs in # groups|# jobs in @ groups|@ completed|queued #@|retry: @|/@ env steps|@ episodes|\(n=@\)|"
         r"@/# reached|#/@ reached", 0.0),
        (r"^job ID completed: .*return @", 8.0), (r"return @|return # ± @|random policy @|^algo=", 0.3),
        (r"@", None)]  # fmt: skip
FULL_ONLY = re.compile(r"^\S+ running: |^\s*│ (?!algo=)|^\s*│\s+│")
JSON_KEY = re.compile(r'"([A-Za-z_]\w*)"\s*:')


def documented(prefix: str, containing: str = "") -> str:
    """The first documented command that starts with ``prefix`` and contains ``containing`` (never a line number:
    the docs move)."""
    found = [c for _, c in COMMANDS if c.startswith(prefix) and containing in c]
    assert found, f"the docs show no command `{prefix} … {containing} …`"
    return found[0]


# the runs other commands read, and the command that writes each: the documented `convoy train … --out PATH`,
# the make targets, and benchmarks/decentralized.py's MA-MeSN-MM run (3 agents on the small treadmill, which
# CoDBC distils)
PRODUCERS = {
    "runs/demo": "make run",
    "runs/demo-distributed": "make run-distributed",
    "runs/bench/decentralized/ma-mesn-mm-2": "convoy train --inprocess --algo ma-mesn-mm $TM --agents 3 "
    "--out runs/bench/decentralized/ma-mesn-mm-2",
}
for _w, _c in COMMANDS:
    learns = _c.startswith("python benchmarks/treadmill_imitation.py") and " --learn " in _c  # clones, then trains
    if (_c.startswith("convoy train") or learns) and " --out runs/" in _c and "--resume" not in _c:
        PRODUCERS.setdefault(_c.split(" --out ")[1].split()[0], _c)
    if _c.startswith("python benchmarks/") and " --json runs/" in _c:  # figures another command reads (--load)
        PRODUCERS.setdefault(_c.split(" --json ")[1].split()[0], _c)
# the seeds of a population that a documented command reads (``runs/…/seed-N/``): the suite's --seeds keeps them
READ_SEEDS: dict[str, set[str]] = {}
for _w, _c in COMMANDS:
    for _path, _seed in re.findall(r"(runs/[\w./-]+?)/seed-(\d+)/", _c):
        READ_SEEDS.setdefault(_path, set()).add(_seed)
JOB_TOML = """# a small job for the docs' `--config job.toml` lines
algo = "idqn"
env = "referential"
steps = 400
num_envs = 8
eval_episodes = 2
algo_params = { hidden = [32], learning_starts = 64 }
"""


def small_steps(n: int) -> int:
    """A few hundred steps, in the order of the docs' own (a resume asks for more than the run it continues)."""
    return int(200 + 100 * math.log2(max(n, 1000) / 1000))


def shrink(argv: list[str]) -> list[str]:
    """The documented argv at a small budget."""
    out, i = [], 0
    while i < len(argv):
        flag = argv[i]
        value = argv[i + 1] if i + 1 < len(argv) else ""
        if flag in ("--steps", "--learn"):
            out += [flag, str(small_steps(int(value)))]
        elif flag in ("--episodes", "--eval-episodes", "--tune-episodes", "--final-episodes"):
            out += [flag, str(min(int(value), 2))]
        elif flag == "--samples":
            out += [flag, str(min(int(value), 200))]
        elif flag == "--actors" and value.isdigit():
            out += [flag, str(min(int(value), 2))]
        elif flag == "--eval-every":
            out += [flag, "200"]
        elif flag == "--seeds":  # the first two (still a population), and those another command reads
            values = list(itertools.takewhile(str.isdigit, argv[i + 1 :]))
            read = READ_SEEDS.get(argv[argv.index("--out") + 1] if "--out" in argv else "", set())
            out += [flag, *values[:2], *(v for v in values[2:] if v in read)]
            i += 1 + len(values)
            continue
        elif flag == "--since":  # a job's rows from the start: a small job has none past the docs' step
            out += [flag, "0"]
        elif flag == "--hp" and value == "compile=true":  # compiling costs ~30 s a run and changes no figure
            out += [flag, "compile=false"]  # (tests/test_update_device.py holds compiled to eager)
        else:
            out.append(flag)
            i += 1
            continue
        i += 2
    if out[:2] == ["convoy", "train"] and "--resume" not in out:
        out += [] if "--steps" in out else ["--steps", "300"]  # the defaults are 100,000s
        out += [] if "--eval-episodes" in out else ["--eval-episodes", "2"]
        out += ["--no-progress"]
        if any(a.startswith("demonstrator=") or a in DEMO_PRESETS for a in out):  # DAgger: minutes a round
            out += ["--hp", "demo_rounds=1", "--hp", "demo_episodes=2"]
    if out[:3] == ["convoy", "env", "rollout"] and "--episodes" not in out:
        out += ["--episodes", "2"]
    if out[:2] == ["convoy", "eval"] and "--episodes" not in out:
        out += ["--episodes", "2"]
    if out[:2] == ["convoy", "analyze"] and "--samples" not in out:
        out += ["--samples", "200"]
    return out


def shrink_toml(text: str) -> str:
    """A sweep file at a small budget: every ``steps`` shrunk, a few evaluation and held-out episodes, few
    checkpoints."""
    text = re.sub(r"\b(steps\s*=\s*)([\d_]+)", lambda m: m[1] + str(small_steps(int(m[2].replace("_", "")))), text)
    text = text.replace("\n[figure]\n", "\n[figure]\nheld_out_episodes = 2\n")
    text = re.sub(r"\b(eval_episodes\s*=\s*)[\d_]+", r"\g<1>2", text)
    return re.sub(r"\b(eval_every|log_every|checkpoint_every)(\s*=\s*)[\d_]+", r"\1\g<2>200", text)


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield workspace(tmp_path_factory.mktemp("docs-run"))


def workspace(root: Path) -> Path:
    """``root`` laid out like the repository's root, as scratch for the documented commands: shrunk sweep files, a
    small ``job.toml``, the benchmark scripts, ``docs/``."""
    (root / "experiments").mkdir()
    for path in (ROOT / "experiments").glob("*.toml"):
        (root / "experiments" / path.name).write_text(shrink_toml(path.read_text()))
    (root / "job.toml").write_text(JOB_TOML)
    (root / "benchmarks").symlink_to(ROOT / "benchmarks")
    (root / "examples").symlink_to(ROOT / "examples")
    (root / "docs").mkdir()
    return root


def run_convoy(argv: list[str], ws: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``convoy ARGV`` in this process with ``ws`` as the working directory: (exit code, stdout + stderr)."""
    import torch._dynamo

    from convoy.cli.main import main

    torch._dynamo.reset()  # each command compiles afresh: dozens of `--hp compile=true` runs in one process would
    # otherwise reach dynamo's recompile limit, and whether they share a worker is the scheduler's choice
    cwd = os.getcwd()
    os.chdir(ws)
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        os.chdir(cwd)
    out = capsys.readouterr()
    return code or 0, out.out + out.err


# benchmark scripts that change no process-wide state (threads, environment variables, signal handlers) and start
# no process of their own code: they run in this process, without the ~3 s of imports a new interpreter pays (47 of
# the documented commands: learner_scores.py alone is 31)
IN_PROCESS = {"learner_scores.py", "treadmill_imitation.py", "treadmill_causes.py", "speaker_listener.py",
              "treadmill_variants.py", "treadmill_references.py", "doc_figures.py"}  # fmt: skip


def run_script(argv: list[str], ws: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``python ARGV`` in this process with ``ws`` as the working directory, as the interpreter would run it: (exit
    code, stdout + stderr), an uncaught exception exiting 1 with its traceback, ``SystemExit("message")`` too."""
    import runpy
    import traceback

    old_argv, cwd = sys.argv, os.getcwd()
    sys.argv = list(argv)
    os.chdir(ws)
    try:
        runpy.run_path(argv[0], run_name="__main__")
        code, tail = 0, ""
    except SystemExit as exc:  # None exits 0, a message exits 1 and is printed
        message = exc.code is not None and not isinstance(exc.code, int)
        code, tail = (1, f"{exc.code}\n") if message else (int(exc.code or 0), "")
    except Exception:
        code, tail = 1, traceback.format_exc()
    finally:
        sys.argv = old_argv
        os.chdir(cwd)
    out = capsys.readouterr()
    return code, out.out + out.err + tail


def run_make(target: str, ws: Path, **variables: str) -> subprocess.CompletedProcess[str]:
    """``make TARGET`` of the repository (its venv as it is: never reinstalled here) with small variables."""
    assigns = [f"{k}={v}" for k, v in variables.items()]
    cmd = ["make", "-C", str(ROOT), "-o", ".venv/.convoy-installed", "BIN=" + str(Path(sys.executable).parent), target]
    return subprocess.run([*cmd, *assigns], capture_output=True, text=True, timeout=600, cwd=ws)


def run_documented(command: str, ws: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """Run one documented command (a ``convoy`` line, a benchmark script or a ``make`` target) at a small budget."""
    argv = shrink(expand(command))
    outputs = {argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("--out", "--json")}
    for arg in set(argv) - outputs:  # a run this command reads: made by the documented command that writes it
        for value in arg.rpartition("=")[2].split(","):  # a path, --hp teacher=PATH or a group LABEL=DIR,DIR
            for path in PRODUCERS:
                if value == path or value.startswith(path + "/"):
                    ensure(path, ws, capsys)
    if argv[0] == "convoy":
        return run_convoy(argv[1:], ws, capsys)
    if argv[0] == "python":
        budget = {"treadmill_search.py": ["--quick", "--episodes", "2", "--tune-episodes", "2"],
                  "treadmill_references.py": ["--episodes", "2"], "treadmill_causes.py": ["--episodes", "2"],
                  "treadmill_imitation.py": ["--rounds", "1", "--epochs", "1", "--episodes", "2",
                                             "--eval-episodes", "2"],
                  "treadmill_variants.py": ["--episodes", "2", "--cache", "variants"],
                  "learner_scores.py": ["--episodes", "2", "--json", "learner_scores.json"],
                  "doc_figures.py": ["--check"],  # never rewrites the repository's docs from a test
                  "env_throughput.py": ["--quick"],
                  "speaker_listener.py": [] if "--load" in argv else ["--quick"],  # --load replays saved figures
                  "ma_mesn_single.py": [],  # its documented 25 k steps take seconds
                  "soak.py": ["--minutes", "0.2", "--jobs", "2", "--sweeps", "1", "--kills", "1", "--burst", "2",
                              "--sample", "2", "--drain", "1.5"],  # bounded: a slow machine leaves jobs queued
                  "treadmill_learning.py": ["--episodes", "2", "--eval-every", "200", "--eval-episodes", "2",
                                                   "--analysis-samples", "256"]}[Path(argv[1]).name]  # fmt: skip
        if Path(argv[1]).name in IN_PROCESS:
            return run_script([*argv[1:], *budget], ws, capsys)
        done = subprocess.run([sys.executable, *argv[1:], *budget], capture_output=True, text=True, timeout=600,
                              cwd=ws)  # fmt: skip
        return done.returncode, done.stdout + done.stderr
    small = {"STEPS": str(small_steps(30_000)), "OUT": str(ws / "runs/demo"), "ARGS": "--eval-episodes 2"}
    if argv[:2] == ["make", "run"]:
        done = run_make("run", ws, **small)
    elif argv[:2] == ["make", "run-distributed"]:
        done = run_make("run-distributed", ws, **small)
    else:
        raise AssertionError(f"no rule to run {command!r}")
    return done.returncode, done.stdout + done.stderr


def ensure(path: str, ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The run at ``ws/path``, made by its documented producer unless it is there: once per test session, kept in
    ``shared_runs`` and copied into every workspace that reads it (each half of the commands has its own workspace,
    and the halves read ~half of the same runs: ~220 s of producers each would run twice)."""
    if made(ws / path):
        return
    kept = shared_runs(ws) / path
    kept.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(f"{kept}.lock"):  # another worker making it: wait for it, then copy
        if not made(kept):
            producer = PRODUCERS[path]
            code, out = run_documented(producer, ws, capsys)
            assert code == 0, f"{producer} (which writes {path}) failed:\n{out[-4000:]}"
            copy_run(ws / path, kept)
    if not made(ws / path):
        copy_run(kept, ws / path)


def made(path: Path) -> bool:
    """A benchmark's figures, a single run, or a population whose seeds need not start at 0, at ``path``."""
    return path.is_file() or (path / "summary.json").is_file() or any(path.glob("seed-*/summary.json"))


def copy_run(src: Path, dst: Path) -> None:
    """A copy, never a link: a documented command may go on with a run in place (``--resume``)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        shutil.copytree(src, dst, dirs_exist_ok=True)
    else:
        shutil.copy2(src, dst)


def shared_runs(ws: Path) -> Path:
    """The folder of this test session's produced runs that every worker's workspace reads from: beside the
    workers' own temporary roots under xdist (their parent is the session's), in the session's root without it."""
    root = ws.parent  # the worker's (or the session's) temporary root: workspaces are made directly in it
    return (root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root) / "docs-run-shared"


def check(where: str, command: str, code: int, out: str, shown: str | None = None) -> None:
    """Exit 0, or for a documented refusal the error the docs show (``shown``: their output line, ids filled in)."""
    shown = OUTPUT.get(where, "") if shown is None else shown
    if shown.startswith("error: "):  # a documented refusal: that error, word for word
        assert code != 0 and shown[len("error: ") :] in " ".join(out.split()), f"{where}: {out[-2000:]}"
    else:
        assert code == 0, f"{where}: `{command}` exited {code}:\n{out[-4000:]}"


@pytest.mark.timeout(1200)  # a hang guard: an 8-agent run's planner references take minutes on a loaded machine
@pytest.mark.parametrize(("where", "command"), FIRST_HALF, ids=[w for w, _ in FIRST_HALF])
def test_every_documented_command_runs(where: str, command: str, ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out = run_documented(command, ws, capsys)
    check(where, command, code, out)


@pytest.mark.parametrize("target", ["run", "run-distributed"])
def test_the_documented_make_targets_run(target: str, ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``make run`` (the quick start) and ``make run-distributed`` at a small STEPS; ``make serve`` runs in the
    service session below and ``make test`` is what runs this."""
    out = ws / "runs" / f"make-{target}"
    # run's references are held against README's block below: its full final evaluation; run-distributed's, short
    evaluation = {} if target == "run" else {"ARGS": "--eval-episodes 2"}
    done = run_make(target, ws, STEPS=str(small_steps(30_000)), OUT=str(out), **evaluation)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    folder = out if target == "run" else Path(f"{out}-distributed")
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["algo"] == "ma-mesn" and summary["env"] == "treadmill" and summary["env_steps"] >= 400
    if target == "run":  # README's block: its references, as each ends and in the table, which no training changes
        shown = next(b for b in BLOCKS.values() if b.doc == "README.md" and b.command == "make run")
        problems = compare([line for line in shown.output if "reference" in line], done.stdout, 0.0)
        assert not problems, "README's make run block:\n" + "\n".join(problems) + "\n\nprinted:\n" + done.stdout


def test_tensorboard_opens_a_run_as_documented(ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """README: ``tensorboard --logdir runs/demo/tb`` serves the run's greedy curve."""
    ensure("runs/demo", ws, capsys)
    port = free_port()
    argv = expand(documented("tensorboard --logdir runs/demo"))
    assert argv[:2] == ["tensorboard", "--logdir"]
    exe = Path(sys.executable).parent / "tensorboard"
    with open(ws / "tensorboard.log", "w") as log:
        proc = subprocess.Popen([str(exe), *argv[1:], "--port", str(port), "--host", "127.0.0.1"], cwd=ws, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
    try:
        tags: dict[str, Any] = {}
        t_end = time.monotonic() + 180
        while time.monotonic() < t_end and not tags:
            with contextlib.suppress(httpx.HTTPError, json.JSONDecodeError):
                tags = httpx.get(f"http://127.0.0.1:{port}/data/plugin/scalars/tags", timeout=10).json()
            time.sleep(0.5)
        assert any("eval/return" in run for run in tags.values()), (tags, (ws / "tensorboard.log").read_text())
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)


def test_the_documented_hosts_run_a_job_through_a_router(ws: Path) -> None:
    """docs/training.md's many-hosts lines on 127.0.0.1: a router, a learner host, an actor host; the job ends."""
    lines = [documented("convoy router"), documented("convoy host", "--roles learner"),
             documented("convoy host", "--roles actor")]  # fmt: skip
    port = free_port()

    def local(command: str) -> list[str]:
        text = re.sub(r"tcp/[0-9.]+:7447", f"tcp/127.0.0.1:{port}", command)
        return [sys.executable, "-m", "convoy.cli", *shrink(shlex.split(text))[1:]]

    procs = []
    try:
        for i, command in enumerate(lines):
            with open(ws / f"host-{i}.log", "w") as log:
                procs.append(subprocess.Popen(local(command), cwd=ws, stdout=log, stderr=subprocess.STDOUT,
                                              start_new_session=True))  # fmt: skip
        learner = procs[1]
        assert learner.wait(300) == 0, (ws / "host-1.log").read_text()[-4000:]
        summary = json.loads((ws / "runs/run7/summary.json").read_text())
        assert summary["env_steps"] >= 400
    finally:
        for proc in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)


class Session:
    """A documented service session: ``convoy serve`` started as shown (on a free port), then each line in order,
    the docs' example ids replaced by those the service gave."""

    ID = re.compile(r"\b([a-z][a-z-]*?)-([0-9a-f]{6})\b")

    def __init__(
        self, ws: Path, capsys: pytest.CaptureFixture[str], keep_steps: set[str] = frozenset(), full: bool = False
    ) -> None:
        """``keep_steps``: the names of the jobs that keep their documented steps; ``full``: every command and job at
        the docs' own budget (and the outputs' figures compared, ``FULL``)."""
        ws.mkdir()
        shutil.copytree(ROOT / "experiments" if full else ws.parent / "experiments", ws / "experiments")
        self.ws, self.capsys, self.keep_steps, self.full = ws, capsys, keep_steps, full
        self.printed: dict[str, str] = {}  # each line's output, by where
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env: dict[str, str] = {}
        self.seen: dict[str, str] = {}
        self.service: Service | None = None
        self.problems: list[str] = []  # where an output disagrees with the docs' (all of them, then one failure)

    @staticmethod
    def lines(doc: str) -> list[tuple[str, str]]:
        return [(w, c) for w, c in COMMANDS if w.startswith(doc + ":") and c.startswith(SERVICE)]

    def auth(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.env['TOKEN']}"}

    def post(self, path: str) -> None:
        r = httpx.post(self.url + path, headers=self.auth(), timeout=60)
        assert r.status_code < 400, r.text

    def wait_state(self, name: str, states: set[str], timeout: float = 240) -> None:
        """Until the job ``name`` names is in one of ``states``."""
        job = self.seen[name]
        t_end, state = time.monotonic() + timeout, None
        while time.monotonic() < t_end:
            state = httpx.get(f"{self.url}/jobs/{job}", timeout=30).json()["state"]
            if state in states:
                return
            time.sleep(0.3)
        raise AssertionError(f"{job} still {state} after {timeout:g} s")

    def wait_steps(self, name: str, steps: int, timeout: float = 240) -> None:
        """Until the job ``name`` names has ``steps`` env steps."""
        job = self.seen[name]
        t_end, done = time.monotonic() + timeout, 0
        while time.monotonic() < t_end:
            done = httpx.get(f"{self.url}/jobs/{job}", timeout=30).json()["progress"].get("env_steps") or 0
            if done >= steps:
                return
            time.sleep(0.3)
        raise AssertionError(f"{job} has {done} env steps after {timeout:g} s, not {steps}")

    def wait_evaluation(self, timeout: float = 240) -> None:
        """Until the last evaluation started has ended."""
        url = f"{self.url}/jobs/{self.seen['referential']}-000/evaluations/{self.seen['evaluation']}"
        t_end, state = time.monotonic() + timeout, None
        while time.monotonic() < t_end:
            state = httpx.get(url, timeout=30).json()["state"]
            if state != "running":
                return
            time.sleep(0.3)
        raise AssertionError(f"evaluation {url} still {state} after {timeout:g} s")

    def sweep(self, path: str) -> None:
        """A referential sweep submitted and watched to its end, as the guide does."""
        self.run("", f"convoy sweep submit {path}")
        self.run("", f"convoy sweep watch {self.seen['referential']}")

    def substitute(self, command: str) -> str:
        text = re.sub(r"(localhost|127\.0\.0\.1):8000", f"127.0.0.1:{self.port}", command)
        text = text.replace("--port 8000", f"--port {self.port}")
        text = text.replace("SWEEP_ID", self.seen.get("referential", "SWEEP_ID"))
        text = re.sub(r"/evaluations/[0-9a-f]{6}", lambda m: f"/evaluations/{self.seen.get('evaluation', '')}", text)
        return self.ID.sub(lambda m: self.seen.get(m[1], m[0]), text)

    def remember(self, out: str) -> None:
        for m in self.ID.finditer(out):
            self.seen[m[1]] = m[0]
        with contextlib.suppress(json.JSONDecodeError, AttributeError):
            body = json.loads(out)
            if isinstance(body, dict) and "request" in body and re.fullmatch(r"[0-9a-f]{6}", body.get("id", "")):
                self.seen["evaluation"] = body["id"]

    def serve(self, command: str) -> None:
        """``convoy serve …`` / ``make serve`` as a process (its token written under --data, as a user's is)."""
        data = self.ws / "runs/service"
        if command.startswith("make"):
            cmd = ["make", "-C", str(ROOT), "-o", ".venv/.convoy-installed", f"BIN={Path(sys.executable).parent}",
                   "serve", f"PORT={self.port}", f"DATA={data}"]  # fmt: skip
        else:
            argv = shlex.split(self.substitute(command))
            cmd = [sys.executable, "-m", "convoy.cli", *argv[1:]]
        cmd_env = {k: v for k, v in os.environ.items() if k != "CONVOY_API_TOKEN"}
        log = open(self.ws / "serve.log", "ab")  # noqa: SIM115
        proc = subprocess.Popen([*cmd, "--max-processes", "12"] if cmd[0] != "make" else cmd, cwd=self.ws,
                                env=cmd_env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
        log.close()
        self.service = Service(data, port=self.port)
        self.service.proc = proc
        t_end = time.monotonic() + 120
        while time.monotonic() < t_end:
            with contextlib.suppress(httpx.TransportError):
                if self.service.client.get("/healthz").status_code == 200:
                    self.env["TOKEN"] = (data / "api_token").read_text().strip()  # the guide's TOKEN=$(cat …)
                    return
            assert proc.poll() is None, (self.ws / "serve.log").read_text()[-3000:]
            time.sleep(0.2)
        raise AssertionError("convoy serve did not answer within 120 s")

    def stop(self) -> None:
        if self.service is not None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.service.proc.pid, signal.SIGTERM)  # make serve: make and its convoy serve
            self.service.stop()

    def export(self, command: str) -> None:
        token = (self.ws / "runs/service/api_token").read_text().strip()
        for name, value in re.findall(r"(\w+)=(\S+)", command):
            self.env[name] = token if value.startswith("$(cat") else value.replace(":8000", f":{self.port}")
        self.env["TOKEN"] = token

    def curl(self, command: str) -> tuple[int, str]:
        """curl's flags the docs use (-s -X -H -d -o -N), sent with httpx; ``| grep X`` filters the answer."""
        command, _, grep = command.partition(" | grep ")
        text = re.sub(r"\$(\w+)", lambda m: self.env.get(m[1], ""), self.substitute(command))
        argv = shlex.split(text)[1:]
        method, headers, data, out, url = "GET", {}, None, None, ""
        i = 0
        while i < len(argv):
            a = argv[i]
            if a in ("-X", "-H", "-d", "-o"):
                v = argv[i + 1]
                i += 1
                if a == "-X":
                    method = v
                elif a == "-H":
                    k, _, hv = v.partition(":")
                    headers[k.strip()] = hv.strip()
                elif a == "-d":
                    body = json.loads(v)
                    kept = self.full or body.get("name") in self.keep_steps
                    data = json.dumps(body if kept else shrink_body(body))
                    method = "POST" if method == "GET" else method
                else:
                    out = v
            elif not a.startswith("-"):
                url = a if a.startswith("http") else f"http://{a}"
            i += 1
        with httpx.Client(timeout=60) as client:
            if "/events" in url:  # a live stream: it opens with its retry line
                with client.stream(method, url, headers=headers) as r:
                    first = next(line for line in r.iter_lines() if line)
                    assert r.headers["content-type"].startswith("text/event-stream"), r.headers
                    return r.status_code, first
            r = client.request(method, url, headers=headers, content=data)
        if out:
            (self.ws / out).write_bytes(r.content)
            return r.status_code, f"{len(r.content)} bytes"
        body = r.text
        if grep:
            body = "\n".join(line for line in body.splitlines() if grep.strip() in line)
        return r.status_code, body

    def run(self, where: str, command: str) -> None:
        if command.startswith(("convoy serve", "make serve")):
            return self.serve(command)
        if command.startswith("export "):
            return self.export(command)
        if command.startswith("curl "):
            status, out = self.curl(command)
            shown = OUTPUT.get(where, "")
            refused = shown.startswith('{"field"')
            assert (400 <= status < 500) if refused else status < 400, f"{where}: {status} {out[:2000]}"
            assert out, f"{where}: an empty answer"
            self.printed[where] = out
            self.compare_answer(where, out)
            self.remember(out)
            return None
        argv = shlex.split(self.substitute(command))
        argv = argv if self.full else shrink(argv)
        env = {"CONVOY_API_URL": self.url, "CONVOY_API_TOKEN": self.env.get("CONVOY_API_TOKEN", self.env["TOKEN"]),
               "COLUMNS": "200"}  # the docs' tables at their natural width  # fmt: skip
        with mock.patch.dict(os.environ, env):
            code, out = run_convoy(argv[1:], self.ws, self.capsys)
        check(where, command, code, out, shown=self.substitute(OUTPUT.get(where, "")))  # the ids the service gave
        block = BLOCKS.get(where)
        self.printed[where] = out
        if block is not None and not block.output[0].startswith("error: "):  # a refusal: word for word, above
            skip, rules = (FULL_ONLY, FULL) if self.full else (SESSION_ONLY, SESSION)
            shown = [line for line in block.output if not skip.search(line)]
            self.problems += [f"{where} `{command}`: {p}" for p in compare(shown, out, None, rules)]
        self.remember(out)
        return None

    def assert_agrees(self) -> None:
        """Every disagreement with the docs at once, with what the lines concerned printed."""
        problems = "\n".join(self.problems)
        printed = "\n".join(f"{where}:\n{out}" for where, out in self.printed.items() if where and where in problems)
        assert not problems, f"what the docs show and the session printed disagree:\n{problems}\n\nprinted:\n{printed}"

    def compare_answer(self, where: str, out: str) -> None:
        """A curl answer against the docs': a refusal word for word; a JSON answer has every key the docs show
        (their values are one session's, trimmed); a text answer (the SSE stream's first line, Prometheus' lines)
        by template."""
        block = BLOCKS.get(where)
        if block is None:
            return
        shown = "\n".join(block.output)
        if shown.startswith('{"field"'):
            if json.loads(shown) != json.loads(out):
                self.problems.append(f"{where}: the docs show the refusal {shown}, the service answered {out}")
        elif shown.startswith("{"):
            missing = set(JSON_KEY.findall(shown)) - set(JSON_KEY.findall(out))
            if missing:
                self.problems.append(f"{where}: the answer has none of {sorted(missing)}: {out[:1000]}")
        else:
            self.problems += [f"{where}: {p}" for p in compare(block.output[:1], out, None, SESSION)]


def shrink_body(body: Any) -> Any:
    """A documented REST body at a small budget (its steps and episodes)."""
    if isinstance(body, dict):
        small = {"steps": lambda n: small_steps(n), "episodes": lambda n: min(n, 2)}
        return {k: small[k](v) if k in small and isinstance(v, int) else shrink_body(v) for k, v in body.items()}
    return body


def test_the_readme_service_session_runs(ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """README's service lines in their order against a real ``convoy serve`` (jobs and the sweep at small steps)."""
    session = Session(ws / "readme", capsys)
    try:
        for where, command in session.lines("README.md"):
            session.run(where, command)
    finally:
        session.stop()
    session.assert_agrees()


@pytest.mark.docs_budget("docs/service.md's session: its jobs and sweep at their steps, 5–10 min on 2 cores")
@pytest.mark.timeout(1800)
def test_the_service_guide_session_at_its_budget(ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The guide's session as the guide runs it, every job at its documented steps: what each command prints
    against what the guide shows, its figures within ``FULL``'s tolerances."""
    guide_session(Session(ws / "guide-full", capsys, full=True))


def test_the_service_guide_session_runs(ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """docs/service.md's lines in their order. What the guide's story takes for granted is arranged between them:
    the demo job keeps its 60,000 steps (the guide stops it) and is stopped once the guide is done with it; the
    lines after its submission wait for "running" and its resume for "stopped", as the guide's comments say; the
    sweep job it evaluates and scales is one of a finished referential sweep (the guide shows that sweep later)."""
    guide_session(Session(ws / "guide", capsys, keep_steps={"demo"}))


def guide_session(session: Session) -> None:
    """docs/service.md's lines in their order, and the service's log against the guide's (``make serve``)."""
    try:
        for where, command in session.lines("service.md"):
            if command.startswith("curl -s localhost:8000/jobs/demo-") and command.count("/") == 2:  # "6 s later"
                session.wait_state("demo", {"running"})
            if "/resume" in command:  # "then stopped …, checkpoint written"
                session.wait_state("demo", {"stopped"})
            if "/metrics?since=" in command:  # the rows the guide shows are there
                session.wait_steps("demo", int(BLOCKS[where].output[-1].split('"last_step":')[1].rstrip("}")))
            if "/evaluations/" in command:  # "4 s later": it has ended
                session.wait_evaluation()
            if "referential-" in command and "finished" not in session.seen:
                session.sweep("experiments/referential.toml")
                session.seen["finished"] = session.seen["referential"]
            session.run(where, command)
            if "-o demo.pt" in command:  # the guide is done with the demo job
                session.post(f"/jobs/{session.seen['demo']}/stop")
    finally:
        session.stop()
    serve = next(BLOCKS[w] for w, c in session.lines("service.md") if c.startswith("make serve"))

    def plain(text: str) -> str:  # the token, the data folder and the repository's place are the session's own
        return re.sub(r"(api_token\)): \S+", r"\1: TOKEN", text.replace(f"{session.ws}/", "").replace(f"{ROOT}/", ""))

    log = plain((session.ws / "serve.log").read_text())
    problems = compare([plain(line) for line in serve.output], log, None, [(r"@", None)])
    session.problems += [f"{serve.where} (the service's log): {p}" for p in problems]
    session.assert_agrees()
