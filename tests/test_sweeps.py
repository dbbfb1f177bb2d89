"""Sweeps through the job service: a grid of real jobs, its summary with CIs over seeds, a restart in the middle,
and clear errors for malformed sweep bodies and files."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy import stats

from convoy.api.sweeps import busy_seconds
from convoy.cli.main import main
from convoy.cli.sweep_file import load_sweep, read_file
from convoy.validation import ConfigError
from tests.service_fixture import AUTH, TOKEN, Service

pytestmark = pytest.mark.timeout(600)

TINY: dict[str, Any] = {
    "name": "tiny",
    "base": {
        "env": "referential",
        "steps": 3_000,
        "num_envs": 8,
        "eval_every": 1_000,
        "eval_episodes": 16,
        "log_every": 500,
        "checkpoint_every": 1_000,
        "algo_params": {"hidden": [32], "learning_starts": 200},
    },
    "grid": {"algo": ["ma-mesn", "idqn"], "seed": [0, 1]},
    "threshold": 0.0,
}


def wait_sweep(svc: Service, sweep_id: str, pred: Any, timeout: float, what: str) -> dict[str, Any]:
    t_end = time.monotonic() + timeout
    view: dict[str, Any] = {}
    while time.monotonic() < t_end:
        view = svc.client.get(f"/sweeps/{sweep_id}").json()
        if pred(view):
            return view
        time.sleep(0.5)
    raise AssertionError(f"timed out waiting for {what}: {view}")


def test_a_sweep_runs_through_a_service_restart_and_summarises_its_groups(tmp_path: Path) -> None:
    data = tmp_path / "svc"
    svc = Service(data, max_processes=3).start()  # one job at a time: the others wait in the queue
    again: Service | None = None
    try:
        resp = svc.client.post("/sweeps", json=TINY, headers=AUTH)
        assert resp.status_code == 201, resp.text
        sweep = resp.json()
        sid = sweep["id"]
        assert [m["point"] for m in sweep["jobs"]] == [
            {"seed": 0, "algo": "ma-mesn"}, {"seed": 0, "algo": "idqn"},
            {"seed": 1, "algo": "ma-mesn"}, {"seed": 1, "algo": "idqn"},
        ]  # fmt: skip
        assert sweep["state"] == "running" and sweep["states"] == {"queued": 4}
        wait_sweep(svc, sid, lambda v: v["states"].get("running"), 90, "a job running")
        svc.kill()  # SIGKILL: the queued jobs and the sweep must be found again
        again = Service(data, port=svc.port, max_processes=3).start()
        assert again.client.get(f"/sweeps/{sid}").json()["id"] == sid
        done = wait_sweep(again, sid, lambda v: v["state"] != "running", 420, "the sweep to end")
        assert done["state"] == "completed" and done["states"] == {"completed": 4}, done
        assert 0 < done["busy_s"] <= done["ended_at"] - done["started_at"] + 1e-6, done

        summary = again.client.get(f"/sweeps/{sid}/summary").json()
        assert summary["state"] == "completed" and summary["threshold"] == 0.0
        groups = {g["group"]: g for g in summary["groups"]}
        assert list(groups) == ["algo=ma-mesn", "algo=idqn"]
        for name, group in groups.items():
            assert len(group["jobs"]) == 2 and group["states"] == {"completed": 2}, group
            final = group["final"]
            assert final["n"] == 2, final
            x = np.array(final["values"])
            for job_id, value in zip(group["jobs"], x, strict=True):  # each seed's value is its job's final return
                job = again.client.get(f"/jobs/{job_id}").json()
                assert job["final"]["eval_return"] == pytest.approx(value), (name, job_id)
            assert final["mean"] == pytest.approx(x.mean())
            assert final["ci95"] == pytest.approx(stats.t.ppf(0.975, 1) * x.std(ddof=1) / np.sqrt(2))  # t, not 1.96
            assert group["iqm"]["iqm"] == pytest.approx(x.mean())  # two seeds: nothing to trim
            assert group["iqm"]["low"] <= group["iqm"]["iqm"] <= group["iqm"]["high"], group["iqm"]
            curve = group["curve"]
            assert group["auc"]["n"] == 2 and all(-1e-9 <= a <= 1 + 1e-9 for a in group["auc"]["values"]), group
            assert curve["env_steps"] == sorted(curve["env_steps"]) and len(curve["env_steps"]) >= 3, curve
            assert curve["n"][-1] == 2 and all(1 <= n <= 2 for n in curve["n"]), curve
            th = group["threshold"]  # returns of the referential game are ≥ 0: every seed is at 0 at its first point
            assert th["reached"] == 2 and th["of"] == 2 and th["env_steps"]["n"] == 2, th
        # the CLI reads the same summary and draws it
        png = tmp_path / "sweep.png"
        code = main(["sweep", "summary", sid, "--url", again.url, "--plot", str(png)])
        assert code == 0 and png.stat().st_size > 10_000
        log = (data.parent / f"serve-{svc.port}.log").read_text()
        assert f"sweep {sid}: submitted (4 jobs in 2 groups, their seeds in 2 population jobs), queued" in log
    finally:
        if again is not None:
            again.stop()
        svc.stop()


BAD_BODIES = [
    ({k: v for k, v in TINY.items() if k != "name"}, "name"),
    ({**TINY, "grid": {}}, "grid"),
    ({**TINY, "grid": {"colour": ["red"]}}, "grid.colour"),
    ({**TINY, "grid": {"seed": []}}, "grid.seed"),
    ({**TINY, "grid": {"seed": [1, 1]}}, "grid.seed"),
    ({**TINY, "grid": {"algo": ["ma-mesn", "nope"]}}, "grid.algo"),
    ({**TINY, "grid": {"algo_params.lr": [0.001, -1.0]}}, "grid.algo_params.lr"),
    ({**TINY, "base": {**TINY["base"], "algo_params": {"lr": 7}}}, "base.algo_params.lr"),
    ({**TINY, "base": {**TINY["base"], "steps": 2}}, "base.steps"),
    ({**TINY, "base": {**TINY["base"], "actors": 3}}, "base.actors"),
    ({**TINY, "base": {**TINY["base"], "colour": 3}}, "base.colour"),
    ({**TINY, "grid": {"seed": list(range(40)), "algo_params.lr": [i / 1000 for i in range(1, 40)]}}, "grid"),
    ({**TINY, "actors": 0}, "actors"),
    ({**TINY, "algos": {"ppo": {"lr": 0.1}}}, "algos.ppo"),
    ({**TINY, "algos": {"ma-mesn": {"replay": True}}}, "algos.ma-mesn.replay"),
    ({**TINY, "exclude": [{"seed": 0}]}, "exclude[0]"),
    ({**TINY, "exclude": [{"seed": 7, "algo": "idqn"}]}, "exclude[0].seed"),
    ({**TINY, "exclude": [{"seed": s, "algo": a} for s in (0, 1) for a in ("ma-mesn", "idqn")]}, "exclude"),
]


@pytest.fixture(scope="module")
def quiet_service(tmp_path_factory: pytest.TempPathFactory) -> Any:
    svc = Service(tmp_path_factory.mktemp("sweeps") / "svc", max_processes=3).start()
    try:
        yield svc
    finally:
        svc.stop()


@pytest.mark.parametrize(("body", "field"), BAD_BODIES, ids=[f for _, f in BAD_BODIES])
def test_a_malformed_sweep_body_is_a_4xx_naming_the_field(quiet_service: Service, body: Any, field: str) -> None:
    resp = quiet_service.client.post("/sweeps", json=body, headers=AUTH)
    assert resp.status_code == 422, resp.text
    error = resp.json()
    assert error["field"] == field and error["problem"] and error["fix"], error
    assert quiet_service.client.get("/sweeps").json() == {"sweeps": []}  # nothing half-submitted
    assert quiet_service.client.get("/jobs").json() == {"jobs": []}


def test_an_unknown_sweep_is_a_404(quiet_service: Service) -> None:
    for path in ("/sweeps/nope", "/sweeps/nope/summary"):
        resp = quiet_service.client.get(path)
        assert resp.status_code == 404 and resp.json()["field"] == "id", resp.text
    assert "GET /sweeps" in quiet_service.client.get("/sweeps/nope").json()["fix"]


SWEEP_FILE = """
name = "tiny"
threshold = 0.5
[base]
env = "referential"
steps = 3000
[base.algo_params]
hidden = [32]
[grid]
algo = ["ma-mesn", "idqn"]
seed = [0, 1]
[scales.quick.base]
steps = 1000
[scales.quick.grid]
seed = [0, 1, 2]
[scales.bad.base]
steps = -5
[figure]
title = "not part of the sweep"
"""


def test_sweep_files_take_scales_and_name_the_bad_field(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "tiny.toml"
    path.write_text(SWEEP_FILE)
    plain = load_sweep(path)
    assert plain["base"]["steps"] == 3000 and plain["grid"]["seed"] == [0, 1] and "figure" not in plain
    quick = load_sweep(path, "quick")
    assert quick["base"]["steps"] == 1000 and quick["base"]["algo_params"] == {"hidden": [32]}
    assert quick["grid"] == {"algo": ["ma-mesn", "idqn"], "seed": [0, 1, 2]}
    with pytest.raises(ConfigError, match=r"no scale 'paper'.*quick, bad"):
        load_sweep(path, "paper")
    with pytest.raises(ConfigError) as bad:
        load_sweep(path, "bad")
    assert bad.value.field == "scales.bad.base.steps"
    broken = tmp_path / "broken.toml"
    broken.write_text(SWEEP_FILE.replace('algo = ["ma-mesn", "idqn"]', 'algo = ["ma-mesn", '))
    json_file = tmp_path / "sweep.json"
    json_file.write_text(json.dumps({"name": "x", "grid": {"seed": [0]}, "actors": "two"}))
    # the CLI checks a file before it sends anything: no service needed for these errors
    cases = [(broken, None, str(broken)), (path, "bad", "scales.bad.base.steps"), (json_file, None, "actors"),
             (tmp_path / "missing.toml", None, "missing.toml")]  # fmt: skip
    for file, scale, field in cases:
        argv = ["sweep", "submit", str(file), "--url", "http://127.0.0.1:9", "--token", TOKEN]
        assert main([*argv, *(("--scale", scale) if scale else ())]) == 2
        err = capsys.readouterr().err
        assert f"error: {field}" in err or (field in err and "cannot read" in err), err
        assert "cannot reach" not in err, err


def test_a_sweep_file_extends_another_with_its_own_grid(tmp_path: Path) -> None:
    """A control file starts from its figure's file (base, scales) and replaces what it names; the figure's
    claims are not inherited; a file that extends itself in a circle is named."""
    (tmp_path / "tiny.toml").write_text(SWEEP_FILE)
    (tmp_path / "cut.toml").write_text('extends = "tiny.toml"\nname = "cut"\n[grid]\nalgo = ["ma-mesn"]\n'
                                       '"algo_params.channel_control" = ["cut"]\n')  # fmt: skip
    quick = load_sweep(tmp_path / "cut.toml", "quick")
    assert quick["name"] == "cut" and quick["base"]["steps"] == 1000
    assert quick["base"] == {"env": "referential", "steps": 1000, "algo_params": {"hidden": [32]}}
    assert quick["grid"] == {"algo": ["ma-mesn"], "algo_params.channel_control": ["cut"], "seed": [0, 1, 2]}
    assert "figure" not in read_file(tmp_path / "cut.toml")
    (tmp_path / "a.toml").write_text('extends = "b.toml"\n')
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    with pytest.raises(ConfigError, match="in a circle"):
        read_file(tmp_path / "a.toml")
    with pytest.raises(ConfigError, match="cannot read"):
        (tmp_path / "c.toml").write_text('extends = "missing.toml"\n')
        read_file(tmp_path / "c.toml")


def test_a_sweeps_busy_time_leaves_out_its_pauses() -> None:
    # two overlapping jobs (0-10, 5-12), a night stopped, then one more (100-130): 12 + 30 seconds of work
    assert busy_seconds([(100.0, 130.0), (0.0, 10.0), (5.0, 12.0), (6.0, 8.0)]) == pytest.approx(42.0)
    assert busy_seconds([]) == 0.0


def test_a_sweeps_view_says_which_dagger_round_a_job_plays_before_its_steps() -> None:
    """A member that starts from a demonstrator shows 0 env steps for its first minutes: the view names its round
    (and `convoy reproduce` prints it) until its Q-learning steps count."""
    from convoy.api.lifecycle import JobRecord, JobState, SweepRecord
    from convoy.api.sweeps import sweep_view

    def rec(job_id: str, progress: dict[str, Any]) -> JobRecord:
        return JobRecord(job_id, JobState.running, {"steps": 100}, 1, 0.0, 1.0, progress=progress)

    demo = {"demo_round": 3, "demo_rounds": 8}
    records = {"a": rec("a", demo), "b": rec("b", {**demo, "env_steps": 40})}
    reader = type("Reader", (), {"get": lambda self, job_id: records[job_id]})()
    sweep = SweepRecord("s", 0.0, {}, [{"id": "a", "point": {"seed": 0}}, {"id": "b", "point": {"seed": 1}}])
    a, b = sweep_view(sweep, reader).jobs
    assert (a.demo_round, a.demo_rounds, a.env_steps) == (3, 8, 0)
    assert (b.demo_round, b.demo_rounds, b.env_steps) == (None, None, 40)


def test_an_algorithms_own_parameters_reach_its_jobs_only() -> None:
    from convoy.api.models import SweepSubmit
    from convoy.api.sweeps import expand

    spec = SweepSubmit(**{**TINY, "grid": {"algo": ["dial", "idqn"], "algo_params.lr": [0.01]},
                          "algos": {"dial": {"replay": True, "lr": 0.5}}})  # fmt: skip
    jobs = {job.config.algo: job.config.algo_params for job in expand(spec)}
    assert jobs["dial"]["replay"] is True and jobs["dial"]["lr"] == 0.01  # the grid's axis wins
    assert "replay" not in jobs["idqn"] and jobs["idqn"]["hidden"] == [32]


def test_excluded_points_are_left_out_of_the_sweep_and_the_rest_pack_as_before() -> None:
    """A sweep's ``exclude`` (runs measured already, e.g. a reproduction's ledger) removes exactly those points."""
    from convoy.api.models import SweepSubmit
    from convoy.api.sweeps import expand

    spec = SweepSubmit(**{**TINY, "exclude": [{"algo": "idqn", "seed": 0}, {"seed": 1, "algo": "ma-mesn"}]})
    assert sorted((j.point["algo"], j.point["seed"]) for j in expand(spec)) == [("idqn", 1), ("ma-mesn", 0)]


def test_a_sweeps_seeds_pack_into_populations_the_limits_allow() -> None:
    """Each group's seeds in populations of at most ``pack`` runs, fewer where the service's limits (which count
    every run's envs) refuse the population; other axes never share a population; pack 1 = one job each."""
    from convoy.api.models import SweepSubmit
    from convoy.api.sweeps import expand, packs
    from convoy.config import ResourceLimits

    spec = SweepSubmit(**{**TINY, "grid": {"algo": ["ma-mesn", "idqn"], "seed": [0, 1, 2, 3, 4]}, "pack": 3})
    jobs = expand(spec)

    def fits(limits: ResourceLimits) -> Any:
        def check(job: Any) -> bool:
            try:
                limits.check(job, "test")
            except ConfigError:
                return False
            return True

        return check

    got = packs(jobs, 3, fits(ResourceLimits()))
    assert sorted(i for p in got for i in p) == list(range(10))
    for pack in got:
        assert len({jobs[i].config.algo for i in pack}) == 1 and len(pack) <= 3
    assert sorted(len(p) for p in got) == [2, 2, 3, 3]
    per_env = jobs[0].config.num_envs * jobs[0].config.agents_per_env()
    assert sorted(len(p) for p in packs(jobs, 3, fits(ResourceLimits(max_agent_envs=2 * per_env)))) == [1] * 2 + [2] * 4
    assert packs(jobs, 1, fits(ResourceLimits())) == [[i] for i in range(10)]
    # hierarchical DQN packs too, save over DIAL (its options are released in lockstep chunks)
    grid = {"algo": ["idqn", "dial"], "seed": [0, 1]}
    hier = expand(SweepSubmit(**{**TINY, "base": {**TINY.get("base", {}), "env": "treadmill", "hierarchical": True},
                                 "grid": grid}))  # fmt: skip
    assert [[hier[i].config.algo for i in p] for p in packs(hier, 3, fits(ResourceLimits()))] == [
        ["idqn", "idqn"], ["dial"], ["dial"]]  # fmt: skip


def test_a_packed_sweeps_summary_reads_as_an_unpacked_ones(tmp_path: Path) -> None:
    """One group of three seeds, packed (one population job, the default) and unpacked (``pack`` 1): the same
    summary layout, each seed its own job with its own folder, checkpoints and final return; a packed seed stops,
    resumes and deletes through its population, and a population that lost a seed says it cannot resume."""
    base = {**TINY["base"], "steps": 2_000, "algo": "idqn"}
    svc = Service(tmp_path / "svc", max_processes=3).start()
    try:
        views = {}
        for pack in (10, 1):
            body = {"name": f"p{pack}", "base": base, "grid": {"seed": [0, 1, 2]}, "pack": pack}
            sid = svc.client.post("/sweeps", json=body, headers=AUTH).json()["id"]
            views[pack] = wait_sweep(svc, sid, lambda v: v["state"] != "running", 300, f"sweep pack={pack}")
            assert views[pack]["state"] == "completed", views[pack]
        jobs = {j["id"]: j for j in svc.client.get("/jobs").json()["jobs"]}
        packed = [jobs[m["id"]] for m in views[10]["jobs"]]
        population = {j["population"] for j in packed}
        assert len(population) == 1 and None not in population, packed
        pop = jobs[population.pop()]
        assert pop["config"]["seeds"] == [0, 1, 2] and pop["state"] == "completed"
        assert pop["members"] == [j["id"] for j in packed]
        for job in packed:
            folder = Path(job["last_checkpoint"]).parent  # in the population's folder, as a run of it
            assert (folder.parent.name, folder.name) == (pop["id"], f"seed-{job['config']['seed']}"), folder
            assert isinstance(job["final"]["eval_return"], float)
            names = {c["name"] for c in svc.client.get(f"/jobs/{job['id']}/checkpoints").json()["checkpoints"]}
            assert "checkpoint.pt" in names
        assert all(jobs[m["id"]]["population"] is None for m in views[1]["jobs"])
        summaries = {p: svc.client.get(f"/sweeps/{v['id']}/summary").json() for p, v in views.items()}

        def layout(x: Any) -> Any:
            if isinstance(x, dict):
                return {k: layout(v) for k, v in x.items() if k not in ("id", "values", "jobs")}
            return [layout(v) for v in x[:1]] if isinstance(x, list) else type(x).__name__

        assert layout(summaries[10]["groups"]) == layout(summaries[1]["groups"])
        assert summaries[10]["groups"][0]["final"]["n"] == 3

        first = packed[0]["id"]  # resumed through its population, which finishes at once (past its budget)
        assert svc.client.post(f"/jobs/{first}/resume", json={}, headers=AUTH).status_code == 200
        svc.wait(pop["id"], lambda v: v["state"] == "completed", timeout=120, what="the resumed population")
        assert svc.client.get(f"/jobs/{first}").json()["state"] == "completed"
        assert svc.client.delete(f"/jobs/{first}", headers=AUTH).status_code == 204
        resp = svc.client.post(f"/jobs/{pop['id']}/resume", json={}, headers=AUTH)
        assert resp.status_code == 409 and "cannot resume" in resp.text, resp.text
    finally:
        svc.stop()


def test_a_success_rates_band_stays_within_zero_and_one(tmp_path: Path, monkeypatch) -> None:
    """The sweep plot drew a t-interval over three seeds from −0.3 to 1.5 on the referential game's success rate,
    where no return lies. A group's summary names the returns its env allows (``bounds``), and the plot clips its
    band to them; a group of an env without bounds (the treadmill) keeps its whole band."""
    from types import SimpleNamespace

    from matplotlib.axes import Axes

    from convoy.analysis.curves import plot_groups
    from convoy.api.lifecycle import JobState
    from convoy.api.sweeps import summarize_group

    def record(env: str, returns: list[float]) -> SimpleNamespace:
        rows = [{"env_steps": 1000 * (i + 1), "eval_return": r} for i, r in enumerate(returns)]
        progress = {"env_steps": 1000 * len(returns), "final": {"eval_return": returns[-1]}}
        return SimpleNamespace(state=JobState.completed, config={"env": env}, rows=rows, progress=progress)

    jobs = {"r0": record("referential", [0.2, 1.0]), "r1": record("referential", [0.9, 1.0]),
            "r2": record("referential", [0.1, 0.2]), "t0": record("treadmill", [10.0, 30.0]),
            "t1": record("treadmill", [12.0, 90.0])}  # fmt: skip
    reader = SimpleNamespace(get=jobs.__getitem__, metrics=lambda job_id, names: jobs[job_id].rows)
    referential = summarize_group(
        "algo=idqn", [(j, {"seed": k}) for k, j in enumerate(("r0", "r1", "r2"))], reader, None
    )
    treadmill = summarize_group("algo=idqn", [("t0", {"seed": 0}), ("t1", {"seed": 1})], reader, None)
    assert referential["bounds"] == [0.0, 1.0] and treadmill["bounds"] is None
    curve = referential["curve"]
    assert curve["mean"][1] - curve["ci95"][1] < 0 < 1 < curve["mean"][1] + curve["ci95"][1]  # the t-interval runs past
    bands = []
    monkeypatch.setattr(Axes, "fill_between", lambda self, x, low, high, **kw: bands.append((list(low), list(high))))
    plot_groups([referential, treadmill], tmp_path / "sweep.png", "sweep")
    (low, high), (t_low, t_high) = bands
    assert min(low) == 0.0 and max(high) == 1.0 and all(0.0 <= v <= 1.0 for v in low + high)
    ci = treadmill["curve"]["ci95"][1]
    assert t_high[1] == pytest.approx(treadmill["curve"]["mean"][1] + ci) and t_low[1] < 0  # not clipped
