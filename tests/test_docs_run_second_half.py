"""The other half of the documented commands that ``test_docs_run.py`` runs (every second one), in a file of its own
so that ``make test`` (``--dist loadfile``) runs the two halves on two workers: together they were ~70 % of the
suite's wall time on one. The same small budget, producers and checks; this file makes its own scratch directory."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.test_docs_run import SECOND_HALF, check, run_documented, workspace

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    yield workspace(tmp_path_factory.mktemp("docs-run-second-half"))


@pytest.mark.timeout(1200)  # a hang guard: an 8-agent run's planner references take minutes on a loaded machine
@pytest.mark.parametrize(("where", "command"), SECOND_HALF, ids=[w for w, _ in SECOND_HALF])
def test_every_documented_command_runs(where: str, command: str, ws: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out = run_documented(command, ws, capsys)
    check(where, command, code, out)
