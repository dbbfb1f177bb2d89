"""Every console block of README.md and docs/ that shows what a command prints agrees with what it prints.

``tests/doc_output.py`` reads the blocks and compares them with a command's output: each documented line with a
printed line of the same template, counts exactly, figures within the tolerance each check below states, timings
never. ``CHECKED`` says where each output block is checked, and ``test_every_output_block_is_checked`` fails on a
block no check names (a new block needs one) and on a check whose block is gone.

Budgets: the population runs and the ``convoy eval`` probes of docs/training.md run here at the budgets the docs
show (seconds; the probes' checkpoint is a 30,000-step run of ~20 s). README's ``make run`` (30,000 steps, 2–3 min
on 2 cores) runs whole only under ``CONVOY_DOCS_BUDGET=1`` (``make docs-check``); in every ``make test`` its
reference rows, which no training changes, are checked on test_docs_run's own small ``make run``, and its prose here
against its block. The service sessions (README, docs/service.md) run in test_docs_run at a small budget, where
each output is compared by template and its budget-free counts exactly; ``make docs-check`` runs the guide's session
at its own budget and compares its figures too (``test_docs_run.FULL`` states their tolerances). A documented
refusal (``error: …``) is compared word for word where its command runs (test_docs_run, test_docs_commands).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.doc_output import Block, compare, numbers, output_blocks, template

ROOT = Path(__file__).resolve().parents[1]
WIDTH = {"COLUMNS": "200"}  # rich lays tables out to the terminal; the docs' are at their natural width

# where each output block is checked: (doc, how its command starts, or a log excerpt's first words) → the check
CHECKED = {
    ("README.md", "make run"): "test_the_make_run_block_at_its_budget (make docs-check); its references: "
    "test_docs_run.test_the_documented_make_targets_run; its prose: test_the_readme_prose_quotes_the_make_run_block",
    ("training.md", "convoy train --inprocess --algo ma-mesn --env referential --steps 3000 --seeds"):
    "test_a_population_run_prints_what_training_md_shows[inprocess]",
    ("training.md", "convoy train --algo ma-mesn --env referential --steps 3000 --seeds"):
    "test_a_population_run_prints_what_training_md_shows[distributed]",
    ("training.md", "convoy eval runs/mm-2/checkpoint.pt"): "test_the_probes_print_what_training_md_shows",
    ("service.md", "make serve"): "test_docs_run.test_the_service_guide_session_runs (the service's log)",
    ("service.md", "log #:#:# job ID: crashed"): "test_api.test_the_service_log_tells_of_a_crash_and_the_respawn",
    ("service.md", "curl "): "test_docs_run's sessions: each answer has the documented keys; a refusal, word for word",
    ("service.md", "convoy jobs "): "test_docs_run.test_the_service_guide_session_runs, by template; its figures: "
    "test_docs_run.test_the_service_guide_session_at_its_budget (make docs-check)",
    ("service.md", "convoy sweep "): "test_docs_run.test_the_service_guide_session_runs, by template; its figures: "
    "test_docs_run.test_the_service_guide_session_at_its_budget (make docs-check)",
}  # fmt: skip


def refusal(block: Block) -> bool:
    """A documented refusal: one ``error: …`` line, which test_docs_run (and test_docs_commands for
    ``convoy train``) compare word for word with what the command prints."""
    return len(block.output) == 1 and block.output[0].startswith("error: ")


def key(block: Block) -> str:
    """A block's command, or for a log excerpt its first line's template (its times and ids are one run's)."""
    return block.command or "log " + template(block.output[0])


def check_of(block: Block) -> str | None:
    found = (how for (doc, start), how in CHECKED.items() if doc == block.doc and key(block).startswith(start))
    return next(found, None)


def test_every_output_block_is_checked() -> None:
    blocks = output_blocks()
    assert len(blocks) >= 30, "the scan found the docs' output blocks"
    unchecked = [f"{b.where}: $ {b.command}" for b in blocks if not refusal(b) and check_of(b) is None]
    assert not unchecked, "output blocks no test compares with what their command prints:\n" + "\n".join(unchecked)
    used = {(doc, start) for doc, start in CHECKED for b in blocks if b.doc == doc and key(b).startswith(start)}
    assert used == set(CHECKED), f"checks whose block is gone: {set(CHECKED) - used}"


def block(doc: str, start: str) -> Block:
    found = [b for b in output_blocks() if b.doc == doc and b.command.startswith(start)]
    assert len(found) == 1, f"{doc}: {len(found)} output blocks under `$ {start}…`"
    return found[0]


def convoy(argv: list[str], cwd: Path, timeout: float = 600) -> str:
    """``convoy ARGV`` as a user runs it (a process, its output to a pipe), stdout and stderr together."""
    env = {**os.environ, **WIDTH}
    env.pop("CONVOY_API_TOKEN", None)
    done = subprocess.run([sys.executable, "-m", "convoy.cli", *argv], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done.stdout + done.stderr


def test_process_events_match_in_any_order_and_a_missing_one_is_reported() -> None:
    documented = ["step 1 · return 0.20", "[exited] actor-0", "[exited] actor-1", "done"]
    printed = "step 1 · return 0.20\n[exited] actor-1\ndone\n[exited] actor-0\n"
    assert compare(documented, printed, 0.0, whole=True) == []
    assert compare(documented, printed.replace("[exited] actor-0\n", ""), 0.0) == ["not printed: '[exited] actor-0'"]
    assert compare(documented[:2] + documented[3:], printed, 0.0, whole=True) == [
        "printed, not documented: '[exited] actor-1'"
    ]


@pytest.mark.parametrize(
    ("start", "figures", "rules"),
    [
        # one process: the same run on every call; 0.1 for another machine's float kernels, which may flip a
        # greedy answer or two of the 100 games behind each success rate
        ("convoy train --inprocess --algo ma-mesn --env referential --steps 3000 --seeds", 0.1, []),
        # actor processes: the transitions the learner has at each update depend on the actors' timing (in four
        # runs seed 2's greedy return was 0.17, 0.17, 0.40 and 0.45; seed 0's 0.53 and 0.21 in two), and so do the
        # policy lag and how many actors have said they are alive at a row: a seed's row is held to its shape and
        # step count, the mean over seeds and the progress lines' returns within 0.3; the mean's CI half-width over
        # three such seeds is not compared (0.36 in the docs, 0.83 in one CI run: Student's t at 2 dof is 4.3)
        ("convoy train --algo ma-mesn --env referential --steps 3000 --seeds", 0.3,
         [(r"actor-@", None), (r"lag @|actors @", None), (r"^# [@#] ± [@#] [@#] \(#\) [@#]$", None),
          (r"^mean over seeds # ± @$", None)]),
    ],
    ids=["inprocess", "distributed"],
)  # fmt: skip
def test_a_population_run_prints_what_training_md_shows(
    start: str, figures: float, rules: list, tmp_path: Path
) -> None:
    shown = block("training.md", start)
    printed = convoy(shown.command.split()[1:], tmp_path)
    whole = "--inprocess" in start  # the distributed run's processes end in either order
    problems = compare(shown.output, printed, figures, rules, whole=whole)
    assert not problems, "\n".join(problems) + "\n\nprinted:\n" + printed


def test_the_probes_print_what_training_md_shows(tmp_path: Path) -> None:
    """The ``convoy eval`` probes on the checkpoint of the ``convoy train`` line above them, all at the documented
    budget. Figures within 0.3 (about one CI half-width: the run's float kernels); the frames of the GIF (one
    episode's length) not compared."""
    producer = re.search(r"\$ (convoy train [^\n]*?--out runs/mm-2[^\n]*)", joined(ROOT / "docs" / "training.md"))
    assert producer, "training.md shows the run its probes evaluate"
    (tmp_path / "docs").mkdir()
    convoy(producer[1].split("#")[0].split()[1:], tmp_path)
    probes = [b for b in output_blocks() if b.doc == "training.md" and b.command.startswith("convoy eval ")]
    assert len(probes) == 3
    for probe in probes:
        printed = convoy(probe.command.split()[1:], tmp_path)
        problems = compare(probe.output, printed, 0.3, [(r"@ frames", None)], whole=True)
        assert not problems, f"{probe.where}:\n" + "\n".join(problems) + "\n\nprinted:\n" + printed


def joined(path: Path) -> str:
    """A Markdown file with its continued console lines (``\\`` at the end) joined."""
    return re.sub(r"\\\n\s*", "", path.read_text())


def test_the_readme_prose_quotes_the_make_run_block() -> None:
    """The paragraph under README's ``make run`` block quotes the block's figures, rounded as written."""
    shown = block("README.md", "make run")
    rows = {}
    for line in shown.output:
        m = re.match(r"│ (.+?)\s+│\s+(.+?) │$", line)
        if m:
            rows[m[1]] = [value for _, value in numbers(m[2])]
    greedy = next(v for k, v in rows.items() if k.startswith("greedy return"))
    prose = (ROOT / "README.md").read_text().split("```", 4)[4]  # after the quick start's two blocks
    prose = " ".join(prose.split("\n\n", 2)[1].split())
    expect = [
        f"greedy return ({greedy[0]:.1f} ± {greedy[1]:.1f},",
        f"random ({rows['reference: random'][0]:.1f} ± {rows['reference: random'][1]:.1f})",
        *(f"{rows[f'reference: {name}'][0]:.1f}" for name in ("private-planner", "team16-planner", "team-planner",
                                                                 "full-planner")),
    ]  # fmt: skip
    constant = next(k for k in rows if k.startswith("reference: constant-"))
    expect.append(f"best constant action ({rows[constant][0]:.1f} ± {rows[constant][1]:.1f})")
    missing = [text for text in expect if text not in prose]
    assert not missing, f"README's prose under `make run` does not quote {missing}:\n{prose}"
    assert f"after {int(rows['env steps'][0]) // 1000} k steps" in prose


@pytest.mark.docs_budget("README's make run: 90,000 steps, ~5 min on 2 cores")
@pytest.mark.timeout(1800)
def test_the_make_run_block_at_its_budget(tmp_path: Path) -> None:
    """README's ``make run`` as the README runs it. Counts exact but the episodes (the policy decides when they
    end: within 10 %); the references exact (played by fixed policies on fixed episodes); the learning figures
    within 30 — another float path is another draw of the run, and the recipe's seeds end at 68–112 (README) —
    and the losses within 3 (they are about 18 at the end)."""
    shown = block("README.md", "make run")
    done = subprocess.run(["make", "-C", str(ROOT), "-o", ".venv/.convoy-installed", "--no-print-directory",
                           f"BIN={Path(sys.executable).parent}", "run", f"OUT={tmp_path / 'demo'}"],
                          capture_output=True, text=True, timeout=1800, env={**os.environ, **WIDTH})  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    printed = done.stdout.replace(str(tmp_path / "demo"), "runs/demo").replace(str(Path(sys.executable).parent),
                                                                                ".venv/bin")  # fmt: skip
    episodes = next(numbers(line)[0][1] for line in shown.output if line.startswith("│ episodes "))
    rules = [(r"reference|^random|^constant|planner|driver", 0.0), (r"^episodes @", 0.1 * episodes), (r"ε @", 0.0),
             (r"loss @", 3.0)]  # fmt: skip
    problems = compare(shown.output, printed, 30.0, rules, whole=True)
    assert not problems, "\n".join(problems) + "\n\nprinted:\n" + printed
