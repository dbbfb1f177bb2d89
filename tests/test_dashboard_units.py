"""The dashboard's formatting of sizes, run in Node: the very function in ``api/static/app.js`` that the browser
runs, without a browser (``test_dashboard.py`` checks the page itself where Chromium is installed)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

APP = Path(__file__).resolve().parents[1] / "api" / "static" / "app.js"
NODE = shutil.which("node") or shutil.which("nodejs")


def js_function(name: str) -> str:
    """The source of top-level ``function name(…) {…}`` in app.js (its body ends at the first ``}`` in column 0)."""
    found = re.search(rf"^function {name}\(.*?^\}}$", APP.read_text(), re.S | re.M)
    assert found, f"app.js has no function {name}"
    return found.group(0)


@pytest.mark.skipif(NODE is None, reason="needs node (apt-get install nodejs)")
def test_checkpoint_sizes_read_as_people_write_them() -> None:
    """A checkpoint's download link read "best.pt (1.32M B)": a count's "M" glued to a byte unit. Sizes now read
    "1.3 MB", "842 kB", "512 B"."""
    sizes = [0, 512, 999, 1000, 842_300, 999_999, 1_320_000, 15_400_000, 2_500_000_000]
    script = f"{js_function('fmtBytes')}\nconsole.log(JSON.stringify({json.dumps(sizes)}.map(fmtBytes)));"
    assert NODE is not None
    shown = json.loads(
        subprocess.run([NODE, "-e", script], capture_output=True, text=True, check=True, timeout=60).stdout
    )
    assert shown == ["0 B", "512 B", "999 B", "1.0 kB", "842 kB", "1.0 MB", "1.3 MB", "15 MB", "2.5 GB"]
    link = re.search(r"a\.textContent = `\$\{c\.name\} \((.*?)\)`", APP.read_text())
    assert link and link.group(1) == "${fmtBytes(c.bytes)}", "the download links show sizes with fmtBytes"


def run_js(script: str) -> Any:  # what the script printed, as JSON
    assert NODE is not None
    done = subprocess.run([NODE, "-e", script], capture_output=True, text=True, check=True, timeout=60)
    return json.loads(done.stdout)


def js_const(name: str) -> str:
    found = re.search(rf"^const {name} = .*;$", APP.read_text(), re.M)
    assert found, f"app.js has no const {name}"
    return found.group(0)


@pytest.mark.skipif(NODE is None, reason="needs node (apt-get install nodejs)")
def test_a_finished_population_job_does_not_wait_for_a_checkpoint() -> None:
    """A completed population job's panel said "no checkpoint yet": its checkpoints are its seeds', each in its
    seed-N folder and downloaded from that seed's job. The row now says so (and links each seed's job); a job that
    ended without a checkpoint says it never had one; only a live job waits for its first."""
    jobs = [
        {"state": "completed", "members": ["idqn-a1b2c3-000", "idqn-a1b2c3-001"]},
        {"state": "running", "members": ["idqn-a1b2c3-000"]},
        {"state": "failed", "members": []},
        {"state": "running"},
    ]
    script = f"{js_const('TERMINAL')}\n{js_function('noCheckpointText')}\n"
    shown = run_js(script + f"console.log(JSON.stringify({json.dumps(jobs)}.map(noCheckpointText)));")
    seeds = "each seed's checkpoints are on its own job"
    assert shown == [f"{seeds} (2): ", f"{seeds} (1): ", "no checkpoint: the job was failed before its first",
                     "no checkpoint yet"]  # fmt: skip
    found = re.search(r"^async function refreshDownloads\(.*?^\}$", APP.read_text(), re.S | re.M)
    assert found, "app.js has no async function refreshDownloads"
    source = found.group(0)
    assert "noCheckpointText(job)" in source and "selectJob(member)" in source and "no checkpoint yet" not in source


@pytest.mark.skipif(NODE is None, reason="needs node (apt-get install nodejs)")
def test_the_sweep_chart_keeps_a_success_rates_band_within_its_bounds() -> None:
    """The sweep chart drew a group's band from its t-interval, −0.3 to 1.5 on a success rate; it now stays within
    the group's ``bounds`` (the summary's, from the env), and a group without bounds keeps its whole band."""
    curve = {"env_steps": [1000, 2000, 3000], "mean": [0.4, None, 0.73], "ci95": [1.08, None, 0.2], "n": [3, 3, 3]}
    groups = [{"curve": curve, "bounds": [0, 1]}, {"curve": curve, "bounds": None}]
    script = f"{js_function('groupBand')}\nconsole.log(JSON.stringify({json.dumps(groups)}.map(groupBand)));"
    clipped, whole = run_js(script)
    assert [[round(v, 6) for v in p] for p in clipped] == [[1000, 0.4, 0, 1], [3000, 0.73, 0.53, 0.93]]
    assert [round(v, 6) for v in whole[0]] == [1000, 0.4, -0.68, 1.48]
    assert "groupBand(g)" in js_function("drawSweep")
