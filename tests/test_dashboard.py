"""The dashboard in a real browser: headless Chromium (Debian's ``chromium``, driven by Playwright's Python package
with ``executable_path``) against a real ``convoy serve`` running a real job.

It loads the page, sees the running job's return curve grow, enters the token, clicks Scale and sees the alive
actor count follow, and takes a screenshot: into the test's own directory, or over ``docs/dashboard.png`` (the
picture docs/service.md shows) only when ``CONVOY_UPDATE_SCREENSHOT=1`` asks for it — a test run never rewrites a
tracked file.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

import pytest

from tests.service_fixture import AUTH, SMALL_JOB, TOKEN, Service

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DOCS = Path(__file__).resolve().parents[1] / "docs"

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")

pytestmark = [
    pytest.mark.timeout(240),
    # on a developer's machine a missing browser skips (said in the summary); in CI it fails: a skipped dashboard
    # test there would pass a broken dashboard
    pytest.mark.skipif(
        CHROMIUM is None and not IN_CI, reason="needs Debian's chromium (apt-get install chromium; .ci/run does)"
    ),
]


def test_ci_has_the_browser_the_dashboard_tests_need() -> None:
    assert CHROMIUM is not None, "CI=true but no chromium on PATH: apt-get install chromium, as .ci/run does"


def test_dashboard_shows_a_growing_curve_and_scales_a_job(tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    svc = Service(tmp_path / "svc").start()
    try:
        resp = svc.client.post(
            "/jobs", json={**SMALL_JOB, "steps": 2_000_000, "actors": 1, "name": "demo"}, headers=AUTH
        )
        job = resp.json()["id"]
        svc.wait(job, lambda v: v["state"] == "running" and v["progress"]["env_steps"] > 2000, what="running")
        errors: list[str] = []
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(svc.url + "/")
            page.wait_for_selector(f'#jobs [data-job-id="{job}"]')
            page.wait_for_function(f"window.convoy && window.convoy.selected === {job!r}")
            page.wait_for_function("window.convoy.points.return >= 2", timeout=30_000)
            first = page.evaluate("window.convoy.points.return")
            page.wait_for_function(f"window.convoy.points.return > {first}", timeout=30_000)  # the curve grows
            page.wait_for_function("window.convoy.points.eval_return >= 1", timeout=60_000)  # the greedy curve

            page.fill("#token", TOKEN)
            page.fill("#actors-input", "2")
            page.click("#scale-btn")
            page.wait_for_function("document.querySelector('#actors-alive').textContent.trim() === '2'", timeout=30_000)
            assert svc.client.get(f"/jobs/{job}").json()["actors"] == 2
            page.wait_for_timeout(1500)  # one more redraw of every chart for the picture
            shot = DOCS / "dashboard.png" if os.environ.get("CONVOY_UPDATE_SCREENSHOT") == "1" else tmp_path / "d.png"
            page.screenshot(path=str(shot))
            browser.close()
        assert not errors, errors
        assert shot.stat().st_size > 10_000
    finally:
        svc.stop()


SWEEP = {
    "name": "dash",
    "base": {"env": "referential", "steps": 3_000, "num_envs": 8, "eval_every": 1_000, "eval_episodes": 16,
             "log_every": 500, "checkpoint_every": 1_000, "algo_params": {"hidden": [32], "learning_starts": 200}},
    "grid": {"algo": ["ma-mesn", "idqn"], "seed": [0, 1]},
}  # fmt: skip


def test_dashboard_draws_a_sweep_with_ci_bands_and_acts_on_a_finished_job(tmp_path: Path) -> None:
    from playwright.sync_api import sync_playwright

    svc = Service(tmp_path / "svc", max_processes=3).start()
    try:
        sweep = svc.client.post("/sweeps", json=SWEEP, headers=AUTH).json()
        sid, first = sweep["id"], sweep["jobs"][0]["id"]
        svc.wait_for(f"/sweeps/{sid}", lambda v: v["state"] == "completed", timeout=240, what="the sweep")
        errors: list[str] = []
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 1100})
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.on("dialog", lambda dialog: dialog.accept())  # the Delete button asks first
            page.goto(svc.url + "/")
            page.fill("#token", TOKEN)

            # the sweep: two groups, each a mean curve with its CI band; a ticked job overlays its own curve
            page.click(f'#sweeps [data-sweep-id="{sid}"]')
            page.wait_for_function("window.convoy.sweep.groups === 2 && window.convoy.sweep.bands === 2")
            legend = page.inner_text("#sweep-legend")
            assert "algo=ma-mesn (n=2)" in legend and "algo=idqn (n=2)" in legend, legend
            page.click(f'#jobs [data-job-id="{first}"] input[type=checkbox]')
            page.wait_for_function("window.convoy.sweep.overlays === 1")
            shot = (
                DOCS / "dashboard-sweep.png"
                if os.environ.get("CONVOY_UPDATE_SCREENSHOT") == "1"
                else tmp_path / "s.png"
            )
            page.locator("#sweeps-card").screenshot(path=str(shot))

            # a finished job: its final evaluation, its checkpoints to download, its log, a new evaluation
            page.click(f'#jobs [data-job-id="{first}"] td.id')
            page.wait_for_function(f"window.convoy.selected === {first!r}")
            page.wait_for_selector("#job-final:not([hidden])")
            assert "final greedy return" in page.inner_text("#job-final")
            # its greedy chart: the CI band and the references it was scored beside; a link that opens it again
            page.wait_for_function("window.convoy.greedy && window.convoy.greedy.band >= 1 "
                                   "&& window.convoy.greedy.references >= 1")  # fmt: skip
            assert f"job={first}" in page.evaluate("location.hash") and f"sweep={sid}" in page.evaluate("location.hash")
            other = browser.new_page(viewport={"width": 1280, "height": 1100})
            other.goto(f"{svc.url}/#job={first}&sweep={sid}")
            other.wait_for_function(f"window.convoy.selected === {first!r} && window.convoy.sweep.groups === 2")
            other.close()
            # a link to the sweep alone: its chart scrolled into view, no job opened above it (on a page 800 high
            # the sweep card starts below the fold)
            linked = browser.new_page(viewport={"width": 1280, "height": 800})
            linked.on("pageerror", lambda exc: errors.append(str(exc)))
            linked.goto(f"{svc.url}/#sweep={sid}")
            linked.wait_for_function(f"window.convoy.revealed === {sid!r} && window.convoy.sweep.groups === 2")
            linked.wait_for_timeout(2500)  # the jobs table's next refresh opens no job either
            assert linked.evaluate("window.convoy.selected") is None
            box = linked.evaluate(
                "[document.querySelector('#sweep-figure').getBoundingClientRect().toJSON(), innerHeight]"
            )
            assert box[0]["top"] >= 0 and box[0]["bottom"] <= box[1] and box[0]["height"] > 200, box
            linked.close()
            page.wait_for_selector('#job-downloads a[href$="checkpoints/checkpoint.pt"]')
            link = page.inner_text('#job-downloads a[href$="checkpoints/checkpoint.pt"]')
            assert re.fullmatch(r"checkpoint\.pt \(\d+(\.\d)? [kMG]?B\)", link), link  # "1.3 MB", not "1.32M B"
            page.click("#logs-box summary")
            page.wait_for_function("window.convoy.logs > 0")
            page.fill("#eval-episodes", "8")
            page.click("#eval-btn")
            page.wait_for_function("window.convoy.evaluation && window.convoy.evaluation.state === 'completed'",
                                   timeout=60_000)  # fmt: skip
            assert "over 8 episodes" in page.inner_text("#eval-status")

            # resume it (a completed job continues past its budget: at once complete again), then delete it
            page.click("#resume-btn")
            page.wait_for_function("document.querySelector('#message').textContent.includes('resumed')")
            svc.wait(first, lambda v: v["state"] == "completed", timeout=120, what="the resumed job")
            page.wait_for_function("document.querySelector('#job-state').textContent === 'completed'")
            page.click("#delete-btn")
            page.wait_for_selector(f'#jobs [data-job-id="{first}"]', state="detached")
            browser.close()
        assert svc.client.get(f"/jobs/{first}").status_code == 404
        assert not errors, errors
        assert shot.stat().st_size > 10_000
    finally:
        svc.stop()
