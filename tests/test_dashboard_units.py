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


@pytest.mark.skipif(NODE is None, reason="needs node (apt-get install nodejs)")
def test_the_greedy_chart_fits_its_curve_and_marks_far_references_at_the_edge() -> None:
    """A completed job's greedy chart put a return of ~17 on one axis with references up to 174: the curve and its
    band were a flat line at the bottom. The axis now fits the curve and its band; a reference joins it, nearest
    first, while the curve keeps 1 / REF_ZOOM of its height, and the others are drawn at the edge they lie beyond
    ("▲ scripted 174"). References near the curve are lines on it, as before."""
    curve = [[10_000 * i, 12 + 0.6 * i] for i in range(10)]  # 12 → 17.4
    band = [[x, y - 2, y + 2] for x, y in curve]  # its 95 % CI: 10 → 19.4
    far = [["random", 16.1], ["constant-8", 23.7], ["scripted", 60.1], ["bound", 174.0], ["floor", -500.0]]
    near = [["random", 15.0], ["scripted", 21.0]]
    script = f"{js_function('niceTicks')}\n{js_const('REF_ZOOM')}\n{js_function('yAxis')}\n"
    cases = [[curve, band, far], [curve, band, near], [curve, band, []], [[[0, 5.0]], [], [["bound", 174.0]]]]
    shown = run_js(script + f"console.log(JSON.stringify({json.dumps(cases)}.map((c) => yAxis(...c))));")
    names = [[[name for name, _ in axis[side]] for side in ("shown", "above", "below")] for axis in shown]
    assert names[0] == [["random", "constant-8"], ["scripted", "bound"], ["floor"]]
    assert names[1] == [["random", "scripted"], [], []] and names[2] == [[], [], []]
    assert names[3] == [[], ["bound"], []]  # a single point: the axis fits it, the bound waits at the top
    for axis in shown[:3]:
        lo, hi = axis["ticks"]["lo"], axis["ticks"]["hi"]
        assert lo <= 10 and hi >= 19.4  # the whole band is on the axis
        assert (19.4 - 10) / (hi - lo) >= 0.3, axis["ticks"]  # ... and fills a third of it or more (174: 0.05)
    ticks = shown[0]["ticks"]
    assert all(ticks["lo"] <= v <= ticks["hi"] for _, v in shown[0]["shown"])  # a line only where it is on the axis
    assert all(v > ticks["hi"] for _, v in shown[0]["above"]) and all(v < ticks["lo"] for _, v in shown[0]["below"])
    draw = js_function("drawChart")
    assert "yAxis(points, bandPts, refList)" in draw and "axis.shown" in draw
    assert re.search(r'edge\(axis\.above, .*"▲"\)', draw) and re.search(r'edge\(axis\.below, .*"▼"\)', draw)


@pytest.mark.skipif(NODE is None, reason="needs node (apt-get install nodejs)")
def test_a_sweep_link_shows_the_sweep_and_opens_no_job() -> None:
    """A ``#sweep=ID`` link opened the running (or newest) job, whose panel pushed the sweep's chart below the fold.
    A link naming only a sweep now opens no job and scrolls the sweep's chart into view once drawn; a link naming a
    job opens it (with its sweep selected below it), as before."""
    hashes = ["#sweep=fig8-1a2b3c", "#job=idqn-0a1b2c&sweep=fig8-1a2b3c", "#job=idqn-0a1b2c", "", "#sweep="]
    script = f"{js_function('linkTarget')}\nconsole.log(JSON.stringify({json.dumps(hashes)}.map(linkTarget)));"
    targets = run_js(script)
    assert targets == [
        {"job": None, "sweep": "fig8-1a2b3c", "showSweep": True},
        {"job": "idqn-0a1b2c", "sweep": "fig8-1a2b3c", "showSweep": False},
        {"job": "idqn-0a1b2c", "sweep": None, "showSweep": False},
        {"job": None, "sweep": None, "showSweep": False},
        {"job": None, "sweep": None, "showSweep": False},
    ]
    read, reveal = js_function("readHash"), js_function("revealSweep")
    assert "state.openFirstJob = false" in read and "state.revealSweep = link.sweep" in read
    assert "scrollIntoView" in reveal and '$("sweep-figure")' in reveal
    refresh = re.search(r"^async function refreshJobs\(.*?^\}$", APP.read_text(), re.S | re.M)
    assert refresh and "state.openFirstJob" in refresh.group(0)  # the jobs' first answer opens one only without it
    assert "revealSweep();" in js_function("drawSweep")
