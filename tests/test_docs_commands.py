"""The commands the README and docs/ show exist as written: every ``$ convoy …`` line of their console blocks parses
with the real CLI (its subcommand, flags and choices), every ``convoy train`` and ``convoy jobs submit`` among them
builds a valid job (its ``--set``/``--hp`` names and values), every ``python benchmarks/….py`` line names a script
whose ``--help`` accepts its flags, and every ``make`` target exists. Running them at their own budgets is what
the benchmarks and ``make`` do; the short ones run in the tests of their commands."""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.doc_output import strip_comment

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def console_commands() -> list[tuple[str, str]]:
    """(where, command) for each ``$ `` line of a console block, continuation lines joined, comments dropped."""
    return [(where, command) for where, command, _ in console_blocks()]


def console_blocks() -> list[tuple[str, str, str]]:
    """(where, command, the first line of its output) of each ``$ `` line of a console block."""
    out = []
    for path in DOCS:
        lines = path.read_text().splitlines()
        in_block, i = False, 0
        while i < len(lines):
            line = lines[i]
            if line.startswith("```"):
                in_block = line.strip() == "```console" if not in_block else False
            elif in_block and line.startswith("$ "):
                text, where = line[2:], f"{path.name}:{i + 1}"
                while (text.rstrip().endswith("\\") or text.count('"') % 2) and i + 1 < len(lines):
                    i += 1  # a continued line, or a quoted value that goes on
                    text = text.rstrip().removesuffix("\\") + " " + lines[i].strip()
                shown = lines[i + 1] if i + 1 < len(lines) and not lines[i + 1].startswith(("$ ", "```")) else ""
                out.append((where, strip_comment(text), shown))
            i += 1
    return out


COMMANDS = console_commands()
OUTPUT = {where: shown for where, _, shown in console_blocks()}
CONVOY = [(w, c) for w, c in COMMANDS if c.startswith("convoy ")]
SCRIPTS = [(w, c) for w, c in COMMANDS if c.startswith("python benchmarks/")]
MAKE = [(w, c) for w, c in COMMANDS if c.startswith("make ")]


# a documented shell variable (``TM="…"``, ``LEARNER="…"``): set for the commands after it, not one to run
ASSIGNMENT = re.compile(r"^([A-Z_]+)=(.*)$")


def expand(command: str) -> list[str]:
    """The argv of a documented command, with its shell variables ($TM, $REF, $CONVOY_API_TOKEN, $(cat …)) filled
    from the lines that set them or with placeholders."""
    variables = {}
    for _, c in COMMANDS:
        m = ASSIGNMENT.match(c)
        if m:
            variables[m[1]] = " ".join(shlex.split(m[2]))
    text = re.sub(r"\$\((cat [^)]*)\)", "TOKEN", command)
    text = re.sub(r"\$([A-Z_]+)", lambda m: variables.get(m[1], m[1].lower()), text)
    return shlex.split(text)


def test_the_docs_show_commands() -> None:
    assert len(CONVOY) >= 50 and SCRIPTS and MAKE  # the extraction found the docs' blocks


@pytest.mark.parametrize(("where", "command"), CONVOY, ids=[w for w, _ in CONVOY])
def test_every_documented_convoy_command_parses(where: str, command: str) -> None:
    from convoy.cli.args import in_flag_words
    from convoy.cli.main import build_parser
    from convoy.cli.train import job_from_args
    from convoy.validation import ConfigError

    argv = expand(command)[1:]
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        if exc.code == 0 and "--help" in argv:
            return
        pytest.fail(f"{where}: `{command}` does not parse (exit {exc.code})")
    if argv[0] != "train" or args.resume or (args.config and not Path(args.config).is_file()):
        return  # a placeholder job file, or a run's own job.json (--resume: test_train_cli)
    shown = OUTPUT[where]
    if shown.startswith("error: "):  # a documented refusal: this error, word for word
        with pytest.raises(ConfigError) as info:
            job_from_args(args)
        assert f"error: {in_flag_words(info.value, args)}" == shown, f"{where}: the docs show another error"
    else:
        job_from_args(args)  # the job it asks for is valid: --set and --hp names and values


@functools.cache
def script_help(script: str) -> str:
    """A script's ``--help`` text, read once a worker: the docs run some scripts 30 times, and each start imports
    torch (~3 s)."""
    return subprocess.run([sys.executable, str(ROOT / script), "--help"], capture_output=True, text=True, cwd=ROOT,
                          timeout=120).stdout  # fmt: skip


@pytest.mark.parametrize(("where", "command"), SCRIPTS, ids=[w for w, _ in SCRIPTS])
def test_every_documented_benchmark_takes_its_flags(where: str, command: str) -> None:
    argv = expand(command)
    script = ROOT / argv[1]
    assert script.is_file(), f"{where}: {argv[1]} does not exist"
    flags = [a.split("=")[0] for a in argv[2:] if a.startswith("--")]
    help_text = script_help(argv[1])
    for flag in flags:
        assert flag in help_text, f"{where}: {argv[1]} has no {flag}"


@pytest.mark.parametrize(("where", "command"), MAKE, ids=[w for w, _ in MAKE])
def test_every_documented_make_target_exists(where: str, command: str) -> None:
    targets = set(re.findall(r"^([a-z][a-z-]*):", (ROOT / "Makefile").read_text(), re.M))
    target = shlex.split(command)[1]
    assert target in targets, f"{where}: make {target} is not a target of the Makefile"
