"""A demonstration start (``--hp demonstrator=NAME``): DAgger of a treadmill planner into the Q-network before
Q-learning, each run on its own states; refused where it cannot apply; not repeated when a run goes on."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from convoy.algos.agent import make_agent
from convoy.algos.algorithm import NetworkAgent
from convoy.cli.main import main
from convoy.config import job_config
from convoy.envs import make_batched
from convoy.envs.batched import StepResult
from convoy.learner import imitation
from convoy.learner.imitation import Dagger, demonstration_start, teacher_for
from convoy.validation import ConfigError

DEMO = {"demonstrator": "private-planner", "demo_rounds": 2, "demo_episodes": 6, "demo_epochs": 3}


def test_dagger_records_only_running_envs_and_mixes_teacher_and_student() -> None:
    teacher = lambda obs: np.full(obs.shape[:2], 1)  # noqa: E731
    student = lambda obs: np.full(obs.shape[:2], 2)  # noqa: E731
    obs = np.arange(4 * 3 * 5, dtype=np.float32).reshape(4, 3, 5)
    only_teacher = Dagger(teacher, student, beta=1.0, n_actions=9, envs=4, seed=0, epsilon=0.0)
    assert (only_teacher(obs) == 1).all()
    only_student = Dagger(teacher, student, beta=0.0, n_actions=9, envs=4, seed=0, epsilon=0.0)
    assert (only_student(obs) == 2).all()
    done = np.array([True, False, False, True])
    zeros = np.zeros((4, 3))
    only_student.after_step(StepResult(obs, zeros, done, np.zeros(4, bool), obs))
    only_student(obs)
    (first, second), (labels0, labels1) = only_student.per_run(2)  # run 0: envs 0–1, run 1: envs 2–3
    assert len(first) == 3 and len(second) == 3  # env 0 and env 3 ended after the first step
    np.testing.assert_array_equal(first, obs[[0, 1, 1]])
    np.testing.assert_array_equal(second, obs[[2, 3, 2]])
    assert (np.concatenate([labels0, labels1]) == 1).all()  # the teacher labels every state, whoever drove


def test_each_run_clones_the_planner_from_its_own_states() -> None:
    torch.manual_seed(0)
    job = job_config(algo="idqn", env="treadmill", preset="charger", seeds=[0, 1], algo_params=DEMO)
    env = make_batched(job.env, 1, **job.env_params)
    agent = make_agent(job, env.spec, run_configs=[j.algo_config() for j in job.members()])
    said: list[str] = []
    seen: list[list[dict]] = []
    figures = demonstration_start(agent, job, said.append, after_round=seen.append)
    assert figures is not None and len(figures) == 2 and len(said) == 2 and len(seen) == 2
    for run in figures:
        first, second = run["rounds"]
        assert first["beta"] == 1.0 and second["beta"] == 0.5 and second["states"] > first["states"]
        assert second["accuracy"] > 0.4  # far above chance (1 in 9): the network fits the planner's choices
        assert run["demo_env_steps"] == second["states"] and run["demonstrator"] == "private-planner"
    assert figures[0]["demo_env_steps"] != figures[1]["demo_env_steps"]  # each run played its own episodes
    assert isinstance(agent, NetworkAgent) and agent.target is not None
    for a, b in zip(agent.online.parameters(), agent.target.parameters(), strict=True):
        assert torch.equal(a, b)  # Q-learning bootstraps from the clone
    plain = job_config(algo="idqn", env="treadmill", preset="charger")
    assert demonstration_start(make_agent(plain, env.spec), plain) is None  # no demonstrator: nothing happens


@pytest.mark.parametrize("algo", ["ma-mesn", "ma-bon"])
def test_a_speaker_learns_from_the_listeners_imitation(algo) -> None:
    """MA-MeSN and MA-BoN clone through the channel (straight-through bits): the speakers' weights move too."""
    torch.manual_seed(0)
    demo = {**DEMO, "demonstrator": "planner", "demo_rounds": 1, "demo_episodes": 4, "demo_epochs": 2}
    job = job_config(algo=algo, env="treadmill", preset="charger", algo_params=demo)
    cut = job_config(algo=algo, env="treadmill", preset="charger", algo_params={**demo, "channel_control": "cut"})
    env = make_batched(job.env, 1, **job.env_params)
    agent = make_agent(job, env.spec)
    assert isinstance(agent, NetworkAgent)
    before = [p.detach().clone() for p in agent.online["message"].parameters()]
    figures = demonstration_start(agent, job)
    assert figures is not None and figures[0]["rounds"][0]["accuracy"] > 0.2  # above chance (1 in 9)
    assert figures[0]["demonstrator"] == "team16-planner"  # the planner of what its channel can carry
    after = list(agent.online["message"].parameters())
    assert any(not torch.equal(a, b) for a, b in zip(before, after, strict=True))
    cut_figures = demonstration_start(make_agent(cut, env.spec), cut)
    assert cut_figures is not None and cut_figures[0]["demonstrator"] == "private-planner"  # its sensor alone


def test_planner_names_the_planner_of_the_learners_information() -> None:
    assert teacher_for("planner", {}) == "private-planner"
    assert teacher_for("planner", {"team_sightings": True, "sighting_headings": True}) == "team-planner"
    assert teacher_for("planner", {"team_observations": True}) == "team-planner"
    assert teacher_for("planner", {"team_words": True}) == "team16-planner"
    assert teacher_for("planner", {}, speaks=True) == "team16-planner"  # MA-MeSN, MA-BoN: what 2 bytes carry
    assert teacher_for("full-planner", {}) == "full-planner"  # a named reference is itself
    job_config(algo="idqn", env="treadmill", algo_params={"demonstrator": "planner"})  # accepted


@pytest.mark.parametrize(
    ("values", "says"),
    [
        ({"env": "predator-prey"}, "not for env 'predator-prey'"),
        ({"hierarchical": True}, "hierarchical"),
        ({"algo_params": {"demonstrator": "best-driver"}}, "unknown reference policy 'best-driver'"),
        ({"algo_params": {"demonstrator": "team-planner", "heads": 3}}, "drop heads"),
        ({"algo": "ma-mesn-mm"}, "ma-mesn-mm cannot start from demonstrations"),
    ],
)
def test_a_demonstrator_that_cannot_apply_is_refused_naming_the_field(values, says) -> None:
    job = {"algo": "idqn", "env": "treadmill", "algo_params": {"demonstrator": "private-planner"}, **values}
    with pytest.raises(ConfigError, match=r"algo_params\.demonstrator") as err:
        job_config(**job)
    assert says in str(err.value)


def train_until_the_first_step(monkeypatch, algo: str, out, *hp: str) -> None:
    """``convoy train`` of a 2-seed population started from ``DEMO``, stopped as its first env step begins (the
    machine went away): its clone is checkpointed at step 0 by then."""
    from convoy.actors.stepping import EnvStepper

    args = ["train", "--inprocess", "--algo", algo, "--env", "treadmill", "--preset", "charger", "--seeds", "0",
            "1", "--steps", "256", "--num-envs", "8", "--eval-episodes", "2", "--checkpoint-every", "128",
            "--no-progress", "--out", str(out), "--hp", "hidden=32", "--hp", "learning_starts=64",
            *[a for key, value in DEMO.items() for a in ("--hp", f"{key}={value}")], *hp]  # fmt: skip

    class Stopped(Exception):
        pass

    def stop(*_a, **_k):
        raise Stopped

    with monkeypatch.context() as m:
        m.setattr(EnvStepper, "step", stop)
        with pytest.raises(Stopped):
            main(args)


def test_train_starts_from_the_demonstrator_once_and_a_resume_goes_on(tmp_path, monkeypatch) -> None:
    """The clone is checkpointed before the first step: a run stopped then goes on from it, not from DAgger again."""
    from convoy.algos.checkpoint import load_checkpoint

    out = tmp_path / "run"
    old = torch.get_num_threads()
    try:
        train_until_the_first_step(monkeypatch, "idqn", out)
        for seed in (0, 1):
            demo = json.loads((out / f"seed-{seed}" / imitation.DEMONSTRATION_FILE).read_text())
            assert demo["demo_env_steps"] > 0 and len(demo["rounds"]) == 2
            rounds_s = sum(r["seconds"] for r in demo["rounds"])  # each rounded to 0.1 s, as the total is
            assert demo["demo_s"] >= rounds_s - 0.05 * len(demo["rounds"]) and rounds_s > 0
            assert load_checkpoint(out / f"seed-{seed}" / "checkpoint.pt", device="cpu")[2]["env_steps"] == 0

        def again(*_a, **_k):
            raise AssertionError("a resumed run started from demonstrations again")

        monkeypatch.setattr(imitation, "demonstration_start", again)
        assert main(["train", "--resume", str(out), "--no-progress"]) == 0
    finally:
        torch.set_num_threads(old)
    summary = json.loads((out / "seed-1" / "summary.json").read_text())
    assert summary["env_steps"] >= 256
    assert summary["wall_s"] > summary["clone_s"] == demo["demo_s"]  # the run's clock counts its clone, resumed too


def test_dqfds_margin_asks_the_teachers_action_to_lead_every_other_by_0_8() -> None:
    """``large_margin``: max_a [Q(a) + 0.8·(a ≠ a_E)] − Q(a_E), averaged over samples and agents per run; 0 once the
    teacher's action leads by the margin, whatever the values; actions an agent lacks never count."""
    from convoy.algos.updater import large_margin

    q = torch.tensor([[[[1.0, 0.5, 3.0]], [[2.0, 0.0, 0.0]]]])  # [R=1, b=2, N=1, A=3]
    expert = torch.tensor([[[0], [0]]])
    mask = torch.tensor([[True, True, False]])  # the third action is not this agent's
    # sample 1: the best other is 0.5 + 0.8 = 1.3 → 0.3; sample 2: 2.0 leads 0.8 by more than the margin → 0
    torch.testing.assert_close(large_margin(q, expert, mask), torch.tensor([0.15]))
    assert large_margin(q, expert, torch.ones(1, 3, dtype=torch.bool)).item() == pytest.approx((2.8 + 0) / 2)
    with pytest.raises(ConfigError, match="demo_margin: a margin on demonstrations needs a demonstrator"):
        job_config(algo="idqn", env="treadmill", algo_params={"demo_margin": 1.0})


def test_a_margin_run_keeps_its_demonstrations_with_its_replay_and_refuses_a_resume_without_them(
    tmp_path, monkeypatch, capsys
) -> None:
    """``demo_margin``: the DAgger states and labels are kept (each update draws a batch of them beside the replay's
    and reports the margin), saved with the replay at each checkpoint, so a stopped run goes on with them; a resume
    that would lose them (no replay file) is refused, naming what to do, instead of going on without the margin."""
    import shutil

    out = tmp_path / "run"
    old = torch.get_num_threads()
    try:
        train_until_the_first_step(monkeypatch, "ma-mesn", out, "--hp", "demo_margin=1")
        with np.load(out / "replay.npz") as saved:
            sizes = saved["demos/size"]
            assert saved["demos/data/demo_obs"].shape[:2] == (2, sizes.max())
            assert saved["demos/data/demo_action"].ndim == 3
        demo = [json.loads((out / f"seed-{s}" / imitation.DEMONSTRATION_FILE).read_text()) for s in (0, 1)]
        assert sizes.tolist() == [d["rounds"][-1]["states"] for d in demo]  # every state of the last round
        lost = tmp_path / "lost"
        shutil.copytree(out, lost)
        (lost / "replay.npz").unlink()
        assert main(["train", "--resume", str(lost), "--no-progress"]) != 0
        assert "no demonstrations beside the checkpoint" in capsys.readouterr().err
        assert main(["train", "--resume", str(out), "--no-progress"]) == 0
    finally:
        torch.set_num_threads(old)
    rows = [json.loads(line) for line in (out / "seed-0" / "metrics.jsonl").read_text().splitlines()]
    assert any(r.get("demo_margin", -1) >= 0 for r in rows), "the margin is reported"


def test_a_stop_between_rounds_ends_the_demonstration() -> None:
    """A stopped job's learner asks before each DAgger round (rounds take minutes): it stops there, after the rounds
    already played, instead of cloning on for half an hour as an orphan."""
    job = job_config(algo="idqn", env="treadmill", preset="charger", algo_params={**DEMO, "demo_episodes": 2})
    env = make_batched(job.env, 1, **job.env_params)
    asked: list[int] = []

    def stop() -> bool:
        asked.append(1)
        return len(asked) > 1  # after the first round

    with pytest.raises(imitation.DemonstrationStopped, match="round 2/2"):
        demonstration_start(make_agent(job, env.spec), job, stop=stop)
    assert len(asked) == 2


@pytest.mark.parametrize(
    ("values", "kind"),
    [
        ({"demo_round": 3.0, "demo_rounds": 8.0, "demo_accuracy": 0.7}, "demonstration"),
        ({"demo_round": 0.0, "demo_rounds": 8.0}, "bad"),  # rounds count from 1
        ({"demo_round": 9.0, "demo_rounds": 8.0}, "bad"),
        ({"demo_round": 2.5, "demo_rounds": 8.0}, "bad"),
        ({"demo_round": 1.0, "demo_rounds": 65.0}, "bad"),  # more than a job can ask for
        ({"demo_round": float("nan"), "demo_rounds": 8.0}, "bad"),
        ({"demo_round": 1.0}, "bad"),
    ],
)
def test_a_demonstration_report_is_sorted_by_its_values(values: dict, kind: str) -> None:
    """A learner's DAgger round reaches the job's progress only with values a job can have: well-formed is not
    enough (a hostile or broken learner could send round 9 of 8)."""
    from convoy.protocol import wire
    from convoy.services.jobrunner import MetricReports

    reports = MetricReports()
    msg = wire.Message("metrics", "learner", 0, 0.0, wire.metrics_body("learner", "0", values))
    assert reports.take(msg, set()) == kind
    assert reports.bad == (kind == "bad")


def test_a_service_job_is_running_and_says_its_round_while_it_clones(tmp_path) -> None:
    """Through a real ``convoy serve``: a job that starts from a demonstrator is ``running`` during its DAgger rounds
    (its learner alive, 0 env steps), its progress names the rounds played, the service's log has a line a round,
    and the job then trains to the end."""
    from tests.service_fixture import AUTH, Service

    svc = Service(tmp_path / "svc", max_processes=3).start()
    try:
        body = {"algo": "idqn", "env": "treadmill", "preset": "charger", "steps": 512, "num_envs": 8, "actors": 1,
                "eval_episodes": 2, "log_every": 256, "checkpoint_every": 512, "name": "demo",
                "algo_params": {**DEMO, "demo_episodes": 2, "hidden": [32], "learning_starts": 128}}  # fmt: skip
        job = svc.client.post("/jobs", json=body, headers=AUTH)
        assert job.status_code == 201, job.text
        job_id = job.json()["id"]
        view = svc.wait(job_id, lambda v: v["progress"].get("demo_round") == 2 or v["state"] == "completed",
                        timeout=240, what="the second DAgger round in the job's progress")  # fmt: skip
        assert view["progress"]["demo_rounds"] == 2 and view["state"] in ("running", "completed"), view
        svc.wait(job_id, lambda v: v["state"] in ("completed", "failed"), timeout=240, what="the job's end")
        assert svc.client.get(f"/jobs/{job_id}").json()["state"] == "completed"
        log = (tmp_path / f"serve-{svc.port}.log").read_text()
        assert f"job {job_id}: demonstration round 1/2, clone accuracy" in log, log
        assert log.index(f"job {job_id}: starting → running") < log.index("demonstration round 1/2"), log
    finally:
        svc.stop()
