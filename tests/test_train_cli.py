"""``convoy train``: a real (tiny) run writes its artefacts; bad input is one readable line, exit code 2."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch
from PIL import Image

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.checkpoint import load_checkpoint
from convoy.cli.main import main

TINY = ["--inprocess", "--env", "referential", "--steps", "3000", "--num-envs", "32", "--log-every", "500",
        "--eval-episodes", "50", "--no-progress", "--hp", "hidden=32", "--hp", "learning_starts=64"]  # fmt: skip


def test_train_writes_metrics_curve_checkpoint_and_summary(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["train", "--algo", "ma-mesn", *TINY, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "greedy return" in text and "reference: random" in text and "best greedy point" in text
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) >= 5 and rows[-1]["env_steps"] >= 3000
    curve = [r for r in rows if r.get("eval_return") is not None]  # --eval-every defaults to 10,000: the end only
    assert [r["env_steps"] for r in curve] == [rows[-1]["env_steps"]] and curve[0]["eval_ci95"] >= 0
    assert {"env_steps", "return", "loss", "epsilon", "env_steps_per_s", "updates_per_s"} <= set(rows[0])
    assert (out / "metrics.csv").read_text().startswith("env_steps,")
    assert Image.open(out / "curve.png").size[0] > 400
    summary = json.loads((out / "summary.json").read_text())
    assert summary["env_steps"] >= 3000 and summary["updates"] > 0
    assert set(summary["references"]) == {"random"} and summary["best_eval_step"] == rows[-1]["env_steps"]
    assert load_checkpoint(out / "best.pt", device="cpu")[2]["env_steps"] == summary["best_eval_step"]
    algo, job, counters = load_checkpoint(out / "checkpoint.pt", device="cpu")
    assert job.algo == "ma-mesn" and job.env == "referential" and counters["env_steps"] == summary["env_steps"]
    assert algo.updates == summary["updates"]


def test_config_file_with_flag_overrides(tmp_path, capsys) -> None:
    cfg = tmp_path / "job.toml"
    cfg.write_text('algo = "idqn"\nenv = "treadmill"\nsteps = 999\n[algo_params]\nlr = 0.002\n')
    out = tmp_path / "run"
    assert main(["train", "--config", str(cfg), *TINY, "--checkpoint-every", "1500", "--out", str(out)]) == 0
    _, job, _ = load_checkpoint(out / "checkpoint.pt", device="cpu")
    assert job.algo == "idqn" and job.env == "referential" and job.steps == 3000  # flags win
    assert job.checkpoint_every == 1500
    assert job.algo_params["lr"] == 0.002 and job.algo_params["hidden"] == [32]  # file and flags merge


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--algo", "ppo"], "--algo: unknown algorithm 'ppo'; choose one of: idqn, dqn-ser, dial, ims, ma-mesn"),
        (["--algo", "ims", "--hp", "comm_iterations=0"], "--hp comm_iterations: Input should be greater than or equal"),
        (
            ["--hp", "batch_size=128", "--hp", "replay_capacity=64"],
            "--hp batch_size: 128 is larger than replay_capacity",
        ),
        (["--hp", "lr"], "--hp: expected KEY=VALUE"),
        (["--hp", "gama=0.9"], "--hp gama: unknown parameter for MeSNConfig"),
        (["--env", "referential", "--hierarchical"], "--hierarchical: goals are defined for the treadmill only"),
        (["--steps", "0"], "--steps: Input should be greater than or equal to 1"),
        (["--config", "/nonexistent.json"], "--config: no such file"),
        (["--hp", "hidden=1000000000"], "raise the limit with convoy train --max-layer-width N"),
        (["--max-hidden-weights", "100", "--hp", "hidden=64,64"], "limit max_hidden_weights = 100"),
        (["--max-agent-envs", "0"], "--max-agent-envs: must be ≥ 1"),
        (["--actors", "0"], "--actors: Input should be greater than or equal to 1"),
        (["--agents", "0"], "--agents: Input should be greater than or equal to 1"),
        (["--set", "length=-3"], "--set length: Input should be greater than"),
        (["--runtime", "chunk=-1"], "--runtime chunk: Extra inputs are not permitted"),
    ],
)
def test_bad_train_input_is_one_line(argv: list[str], needle: str, capsys) -> None:
    assert main(["train", "--no-progress", *argv]) == 2
    err = capsys.readouterr().err
    assert needle in " ".join(err.split()), err
    assert "Traceback" not in err


def test_train_help_lists_algorithms_and_hyper_parameters(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    for needle in ("ma-mesn", "ma-bon", "dial", "ims", "dqn-ser", "idqn", "--hp", "comm_iterations", "ser_horizon"):
        assert needle in text


TIMING = {"env_steps_per_s", "updates_per_s", "wall_s"}


def _curve_and_weights(out) -> tuple[list[dict], dict[str, torch.Tensor]]:
    rows = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    algo, _, _ = load_checkpoint(out / "checkpoint.pt", device="cpu")
    assert isinstance(algo, NetworkAgent)
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows], algo.online.state_dict()


def test_the_same_seed_trains_the_same_run(tmp_path, capsys) -> None:
    """Seeds pin everything an in-process run draws (envs, ε-greedy, replay sampling, Gumbel noise, weights): two
    runs of one seed give the same curve and the same weights; another seed does not."""
    runs = {}
    for name, seed in (("a", "0"), ("b", "0"), ("c", "1")):
        out = tmp_path / name
        argv = ["train", "--inprocess", "--algo", "ma-bon", "--env", "treadmill", "--set", "length=30"]
        argv += ["--set", "width=12", "--set", "max_steps=50", "--steps", "2000", "--num-envs", "8", "--seed", seed]
        argv += ["--log-every", "400", "--eval-episodes", "4", "--no-progress", "--hp", "hidden=32,12"]
        argv += ["--hp", "learning_starts=64", "--out", str(out)]
        assert main(argv) == 0, capsys.readouterr().err
        runs[name] = _curve_and_weights(out)
    (curve_a, w_a), (curve_b, w_b), (curve_c, w_c) = runs["a"], runs["b"], runs["c"]
    assert curve_a == curve_b and len(curve_a) >= 5
    for key, value in w_a.items():
        assert torch.equal(value, w_b[key]), key
    assert curve_a != curve_c and any(not torch.equal(v, w_c[k]) for k, v in w_a.items())


def test_the_learning_curve_does_not_change_the_run_it_measures() -> None:
    """Greedy curve points every 500 steps leave training exactly as a run without them: same losses, same weights."""
    from convoy.algos.agent import make_agent
    from convoy.config import job_config
    from convoy.learner.inprocess import Trainer
    from convoy.services.training import make_env

    def train(eval_every: int) -> tuple[list[float], dict[str, torch.Tensor]]:
        hp = {"hidden": 32, "learning_starts": 64}
        job = job_config(algo="ma-mesn", env="referential", steps=3_000, num_envs=32, log_every=500,
                         eval_episodes=20, eval_every=eval_every, algo_params=hp)  # fmt: skip
        env = make_env(job)
        agent = make_agent(job, env.spec)
        result = Trainer(job, env, agent, make_eval_env=lambda n: make_env(job, n), progress=False).run()
        return [r["loss"] for r in result.rows], agent.policy_state()

    with_curve, plain = train(500), train(0)
    assert np.array_equal(with_curve[0], plain[0], equal_nan=True)
    assert all(torch.equal(with_curve[1][k], plain[1][k]) for k in plain[1])


def test_runs_never_share_a_directory_by_accident(tmp_path, capsys, monkeypatch) -> None:
    from convoy.cli.rundir import claim

    out = tmp_path / "run"
    assert main(["train", "--algo", "idqn", *TINY, "--out", str(out)]) == 0
    first = (out / "metrics.jsonl").read_text()
    capsys.readouterr()
    assert main(["train", "--algo", "idqn", *TINY, "--out", str(out)]) == 2  # refused: it holds a run
    err = capsys.readouterr().err
    assert "--out" in err and "holds an earlier run" in err and "--overwrite" in err
    assert (out / "metrics.jsonl").read_text() == first  # nothing lost
    assert main(["train", "--algo", "idqn", *TINY, "--seed", "1", "--out", str(out), "--overwrite"]) == 0
    assert (out / "metrics.jsonl").read_text() != first  # replaced, not interleaved
    capsys.readouterr()

    held = claim(tmp_path / "busy")  # a run in progress holds its directory
    try:
        assert main(["train", "--algo", "idqn", *TINY, "--out", str(tmp_path / "busy"), "--overwrite"]) == 2
        assert "being written by another run" in capsys.readouterr().err
    finally:
        held.release()

    monkeypatch.chdir(tmp_path)  # without --out: the default directory, then a numbered one beside it
    for _ in range(2):
        assert main(["train", "--algo", "idqn", *TINY]) == 0
    assert (tmp_path / "runs/idqn-referential/summary.json").exists()
    assert (tmp_path / "runs/idqn-referential-2/summary.json").exists()


@pytest.mark.parametrize("seeds", [["--seed", "3"], ["--seeds", "3", "5"]], ids=["one-run", "population"])
def test_a_run_goes_on_from_its_folder(tmp_path, capsys, seeds: list[str]) -> None:
    """``--resume DIR`` reads the run's own job.json and checkpoint (and replay, kept here) and goes on to a new
    ``--steps``: the counters carry on, the replay comes back, the metric rows continue without a duplicate, and
    the summary names the algorithm, env, seed and hyper-parameters. A completed run drops its replay by default.
    A run started in this process goes on in this process without being told again."""
    out = tmp_path / "run"
    first = ["train", "--algo", "idqn", *TINY, "--steps", "2000", *seeds, "--out", str(out)]
    assert main(first) == 0
    folders = [out] if seeds[0] == "--seed" else [out / "seed-3", out / "seed-5"]
    assert not list(out.rglob("replay*.npz")), "a completed run keeps its replay only when asked"
    assert main([*first, "--overwrite", "--runtime", "keep_replay=true"]) == 0
    assert list(out.rglob("replay.npz"))
    updates = [json.loads((f / "summary.json").read_text())["updates"] for f in folders]
    capsys.readouterr()
    assert main(["train", "--resume", str(out), "--steps", "4000", "--no-progress"]) == 0
    said = " ".join(capsys.readouterr().out.split())
    assert "started with --inprocess: going on in this process" in said and "Zenoh" not in said, said
    for folder, before, seed in zip(folders, updates, (3, 5), strict=False):
        assert json.loads((folder / "job.json").read_text())["seed"] == seed
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["env_steps"] >= 4000 and summary["algo"] == "idqn" and summary["env"] == "referential"
        assert summary["seed"] == seed and summary["hyper_parameters"]["hidden"] == [32]
        # the replay came back: updates went on at once (32 envs × 2000 steps of data ≥ learning_starts)
        assert summary["updates"] >= 2 * before - 2, (summary["updates"], before)
        steps = [json.loads(line)["env_steps"] for line in (folder / "metrics.jsonl").read_text().splitlines()]
        assert steps == sorted(set(steps)) and steps[-1] >= 4000, steps


def test_resume_says_what_cannot_change(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["train", "--resume", str(out), "--inprocess"]) == 2
    assert "has no job.json" in capsys.readouterr().err
    assert main(["train", "--algo", "idqn", *TINY, "--steps", "1000", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["train", "--resume", str(out), "--inprocess", "--hp", "lr=0.1"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "--resume" in err and "--hp lr cannot change" in err and "--hp compile" in err, err
    from convoy.cli.main import build_parser
    from convoy.cli.train import resumed_job

    args = build_parser().parse_args(
        ["train", "--resume", str(out), "--hp", "compile=true", "--checkpoint-every", "200"]
    )
    job = resumed_job(args)  # how the update runs may change as a long run goes on: what it learns may not
    assert job.algo_params["compile"] is True and job.steps == 1000 and job.algo == "idqn"
    assert job.checkpoint_every == 200  # how often it is saved may change too
    before = (out / "job.json").read_text()
    (out / "checkpoint.pt").rename(out / "stopped-early.pt")  # a run stopped before its first checkpoint
    assert main(["train", "--resume", str(out), "--hp", "compile=true", "--no-progress"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "has no checkpoint.pt to go on from" in err and f"--config {out / 'job.json'}" in err, err
    assert (out / "job.json").read_text() == before, "a refused resume leaves the run's job as it was"
    (out / "stopped-early.pt").rename(out / "checkpoint.pt")
    assert main(["train", "--algo", "idqn", *TINY, "--steps", "1000", "--out", str(out)]) == 2
    assert "--resume" in capsys.readouterr().err  # the refusal to reuse a folder names the way to go on
    (out / "launch.json").write_text("{not json")
    assert main(["train", "--resume", str(out), "--no-progress"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "launch.json (how the run was started) is unreadable" in err and "--inprocess or --actors N" in err, err


def test_one_random_reference_whatever_the_algorithm(tmp_path, capsys) -> None:
    """The random reference is the uniform random policy on the evaluation episodes: the same figure for an
    algorithm with learned messages (DIAL) and one without, and summary.json carries it once."""
    randoms = []
    for algo in ("dial", "idqn"):
        out = tmp_path / algo
        assert main(["train", "--algo", algo, *TINY, "--steps", "600", "--out", str(out)]) == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["random_return"] == summary["references"]["random"][0]
        randoms.append(summary["random_return"])
    assert randoms[0] == randoms[1]


def test_a_policy_that_sends_one_message_is_said_to(tmp_path, capsys) -> None:
    """After training, a message-sending policy whose messages never vary gets a warning (probing them says
    nothing); one whose messages vary does not."""
    from convoy.algos.agent import make_agent
    from convoy.algos.checkpoint import save_checkpoint
    from convoy.algos.nets import GroupLinear
    from convoy.cli.train import warn_constant_messages
    from convoy.config import job_config
    from convoy.envs import make_batched

    job = job_config(algo="ma-mesn", env="referential", algo_params={"hidden": [16]}, device="cpu")
    algo = make_agent(job, make_batched("referential", 1).spec)
    assert isinstance(algo, NetworkAgent)
    path = save_checkpoint(tmp_path / "varied.pt", algo, job, {"env_steps": 0, "episodes": 0, "updates": 0})
    entropy = warn_constant_messages(path)
    assert entropy is not None and entropy > 0.1 and "warning" not in capsys.readouterr().out
    last = list(algo.online["message"].modules())[-1]  # f′'s last layer: every bit's logit pair fixed
    assert isinstance(last, GroupLinear)
    with torch.no_grad():
        for p in last.parameters():
            p.zero_()
        last.bias.view(-1)[0::2] = 5.0
    path = save_checkpoint(tmp_path / "constant.pt", algo, job, {"env_steps": 0, "episodes": 0, "updates": 0})
    assert warn_constant_messages(path) == 0.0
    out = " ".join(capsys.readouterr().out.split())
    assert "warning: every message this policy sent" in out and "says nothing about communication" in out, out


def test_runs_open_in_tensorboard_and_compare_side_by_side(tmp_path, capsys) -> None:
    """Every run writes TensorBoard events (the greedy return with its interval, training figures, speeds, the
    config as hyper-parameters; a resumed run without duplicate steps), and ``convoy compare`` tables and plots
    runs and populations side by side."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    one, pop = tmp_path / "one", tmp_path / "pop"
    base = ["train", "--algo", "idqn", *TINY, "--steps", "2000", "--eval-every", "1000"]
    assert main([*base, "--out", str(one)]) == 0
    assert main(["train", "--resume", str(one), "--steps", "3000", "--inprocess", "--no-progress"]) == 0
    assert main([*base, "--seeds", "1", "2", "--out", str(pop)]) == 0
    events = EventAccumulator(str(one / "tb"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"eval/return", "eval/lower", "eval/upper", "train/loss", "train/epsilon", "speed/env_steps_per_s"} <= tags
    rows = [json.loads(line) for line in (one / "metrics.jsonl").read_text().splitlines()]
    want = [(r["env_steps"], r["eval_return"]) for r in rows if r.get("eval_return") is not None]
    got = [(e.step, e.value) for e in events.Scalars("eval/return")]
    assert [s for s, _ in got] == [s for s, _ in want] and np.allclose([v for _, v in got], [v for _, v in want])
    steps = [e.step for e in events.Scalars("train/loss")]
    assert steps == sorted(set(steps)), "the resumed run's events repeat steps"
    assert any(p.name.startswith("events") for p in (pop / "seed-2" / "tb").iterdir())
    capsys.readouterr()
    png = tmp_path / "cmp.png"
    assert main(["compare", str(one), str(pop), "--plot", str(png)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "final greedy" in out and png.stat().st_size > 10_000
    assert main(["compare", str(tmp_path / "nothing")]) == 2
    assert "holds no run" in capsys.readouterr().err


def fake_run(folder, curve: list[float], final: float) -> None:
    """A run folder as convoy train leaves it, as far as ``convoy compare`` reads one: greedy rows and a summary."""
    folder.mkdir(parents=True)
    rows = [
        {"env_steps": 1000 * (i + 1), "return": 0.0, "eval_return": r, "eval_ci95": 0.5} for i, r in enumerate(curve)
    ]
    (folder / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    summary = {
        "eval_return": final,
        "best_eval_return": max(curve),
        "random_return": 0.25,
        "env_steps": 1000 * len(curve),
    }
    (folder / "summary.json").write_text(json.dumps(summary))


def test_compare_plots_beside_the_runs_and_gives_one_seed_no_ci(tmp_path, capsys, monkeypatch) -> None:
    """``convoy compare`` wrote compare.png into whatever folder it ran in, and showed a single seed as
    ``26.711 ± 0.000``, a CI it does not have. The plot goes beside the runs (or to --plot), one seed's figures
    stand alone, a population's keep their CI."""
    monkeypatch.chdir(tmp_path)
    fake_run(tmp_path / "runs" / "one", [10.0, 26.711], 26.711)
    fake_run(tmp_path / "runs" / "pop" / "seed-1", [8.0, 20.0], 20.0)
    fake_run(tmp_path / "runs" / "pop" / "seed-2", [9.0, 22.0], 22.0)
    assert main(["compare", "runs/one", "runs/pop"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert (tmp_path / "runs" / "compare.png").stat().st_size > 10_000 and not (tmp_path / "compare.png").exists()
    assert "wrote runs/compare.png" in out, out
    assert "26.711" in out and "26.711 ±" not in out and "0.250 ±" not in out.split("runs/pop")[0], out
    assert "21.000 ± " in out and "a group of one seed has no CI over seeds" in out, out
    assert main(["compare", "runs/one", "--plot", "plots/x.png"]) == 0
    assert (tmp_path / "plots" / "x.png").is_file()
    with pytest.raises(SystemExit):
        main(["compare", "--help"])
    assert "compare.png beside the runs" in " ".join(capsys.readouterr().out.split())


@pytest.mark.parametrize("logger", ["wandb", "mlflow"])
def test_a_tracker_that_is_not_installed_is_named_with_its_extra(tmp_path, capsys, monkeypatch, logger: str) -> None:
    import sys

    monkeypatch.setitem(sys.modules, logger, None)  # what `import` sees where the extra is not installed
    assert main(["train", "--algo", "idqn", *TINY, "--logger", logger, "--out", str(tmp_path / "run")]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"loggers: {logger} is not installed: pip install 'convoy[{logger}]'" in err, err
    assert not (tmp_path / "run").exists()  # refused before the run made its folder


def unset(monkeypatch: pytest.MonkeyPatch, *names: str) -> None:
    """The variables are not set for the test; what the code under test sets in-process is undone after it."""
    for name in names:
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)


def test_mlflow_works_as_installed_with_no_environment(tmp_path, monkeypatch) -> None:
    """``--logger mlflow`` with nothing set crashed in the default venv: mlflow-skinny cannot open the
    ``sqlite:///mlflow.db`` store MLflow 3 defaults to, and a file store needs MLFLOW_ALLOW_FILE_STORE. Now each run
    logs into a file store in its own folder (a population's seeds each their own, side by side in one process), and
    nothing lands in the current folder."""
    mlflow = pytest.importorskip("mlflow")
    unset(monkeypatch, "MLFLOW_TRACKING_URI", "MLFLOW_ALLOW_FILE_STORE", "MLFLOW_EXPERIMENT_NAME")
    monkeypatch.chdir(tmp_path)
    one, pop = tmp_path / "one", tmp_path / "pop"
    base = ["train", "--algo", "idqn", *TINY, "--steps", "1000", "--logger", "mlflow"]
    assert main([*base, "--out", str(one)]) == 0
    assert main([*base, "--seeds", "1", "2", "--out", str(pop)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one", "pop"]  # no mlflow.db, no ./mlruns
    for run in (one, pop / "seed-1", pop / "seed-2"):
        client = mlflow.tracking.MlflowClient(tracking_uri=(run / "mlruns").as_uri())
        (found,) = client.search_runs([e.experiment_id for e in client.search_experiments()])
        assert found.info.run_name == run.name and found.info.status == "FINISHED"
        assert found.data.params["seed"] == str(json.loads((run / "job.json").read_text())["seed"])
        history = client.get_metric_history(found.info.run_id, "eval.return")
        assert history and history[-1].step >= 1000 and "final.eval_return" in found.data.metrics


def test_wandb_works_offline_with_no_environment_nor_network(tmp_path, monkeypatch) -> None:
    """``--logger wandb`` with no W&B account, key or variable asked for a key (and failed without a terminal);
    now it runs offline into RUN/wandb, a population's seeds each their own run."""
    pytest.importorskip("wandb")
    unset(monkeypatch, "WANDB_MODE", "WANDB_API_KEY", "WANDB_BASE_URL", "WANDB_DIR", "WANDB_SILENT", "NETRC")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))  # no ~/.netrc key, no ~/.config/wandb settings
    one, pop = tmp_path / "one", tmp_path / "pop"
    base = ["train", "--algo", "idqn", *TINY, "--steps", "1000", "--logger", "wandb"]
    assert main([*base, "--out", str(one)]) == 0
    assert main([*base, "--seeds", "1", "2", "--out", str(pop)]) == 0
    for run in (one, pop / "seed-1", pop / "seed-2"):
        (log,) = (run / "wandb").glob("offline-run-*/run-*.wandb")
        # W&B's service process writes the file; on a loaded machine its last records may land just after
        # finish() returns: wait for them (the 2-minute deadline only stops a hang)
        deadline, data = time.monotonic() + 120, b""
        while not (b"eval/return" in data and b"eval_return" in data) and time.monotonic() < deadline:
            data = log.read_bytes()
            time.sleep(0.2)
        assert b"eval/return" in data and b"eval_return" in data  # its rows, then its summary


@pytest.mark.parametrize(
    ("logger", "env", "needle"),
    [
        ("mlflow", {"MLFLOW_TRACKING_URI": "sqlite:///{tmp}/mlflow.db"}, "pip install mlflow"),
        ("mlflow", {"MLFLOW_TRACKING_URI": "file://{tmp}/store"}, "set MLFLOW_ALLOW_FILE_STORE=true"),
        ("mlflow", {"MLFLOW_ALLOW_FILE_STORE": "false"}, "unset MLFLOW_ALLOW_FILE_STORE"),
        ("wandb", {"WANDB_MODE": "online"}, "run `wandb login` (or set WANDB_API_KEY)"),
    ],
    ids=["mlflow-database", "mlflow-file-store", "mlflow-forbidden", "wandb-online-without-key"],
)
def test_a_tracker_that_cannot_work_is_refused_before_the_run_starts(
    tmp_path, capsys, monkeypatch, logger: str, env: dict[str, str], needle: str
) -> None:
    """One line that says what to set, exit 2, and no half-made run folder (the next run there would be told to
    --resume a run that never trained)."""
    pytest.importorskip(logger)
    unset(monkeypatch, "MLFLOW_TRACKING_URI", "MLFLOW_ALLOW_FILE_STORE", "WANDB_MODE", "WANDB_API_KEY", "NETRC")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for name, value in env.items():
        monkeypatch.setenv(name, value.format(tmp=tmp_path))
    out = tmp_path / "run"
    assert main(["train", "--algo", "idqn", *TINY, "--logger", logger, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert f"loggers: {logger}" in " ".join(err.split()) and needle in " ".join(err.split()), err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("teacher", ["missing", "corrupt"])
def test_a_refused_input_leaves_no_out_folder(tmp_path, capsys, teacher: str) -> None:
    """``convoy train --algo codbc --hp teacher=…`` with a teacher it cannot use exited 2 but left --out behind
    (job.json, empty metrics, tb/), so the next run there was told to --resume a run that never trained."""
    path = tmp_path / "teacher.pt"
    if teacher == "corrupt":
        path.write_bytes(b"not a checkpoint")
    out = tmp_path / "run"
    argv = ["train", "--algo", "codbc", *TINY, "--steps", "500", "--hp", f"teacher={path}", "--out", str(out)]
    assert main(argv) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert f"algo_params.teacher: checkpoint {path}" in err, err
    assert not out.exists()
    assert main(["learner", "--job-id", "refused", "--algo", "codbc", "--env", "referential", "--hp",
                 f"teacher={path}", "--out", str(out)]) == 2  # fmt: skip
    assert not out.exists()


def test_a_run_refused_where_it_runs_removes_the_folder_it_made(tmp_path, capsys, monkeypatch) -> None:
    """Whatever is refused only once the run is under way (here the teacher, with the check before it skipped),
    before its first checkpoint: the folder this command made goes too; a folder that was there keeps what it held
    and loses what the run wrote, so neither reads as a run to resume."""
    from convoy.cli import train
    from convoy.cli.rundir import holds_run

    monkeypatch.setattr(train, "check_job_inputs", lambda job: None)
    out, kept = tmp_path / "run", tmp_path / "kept"
    kept.mkdir()
    (kept / "notes.txt").write_text("mine")
    for where in (out, kept):
        argv = ["train", "--algo", "codbc", *TINY, "--steps", "500", "--hp", f"teacher={tmp_path / 'no.pt'}"]
        assert main([*argv, "--out", str(where)]) == 2
        assert "teacher: checkpoint" in " ".join(capsys.readouterr().err.split())
    assert not out.exists()
    assert (kept / "notes.txt").read_text() == "mine"
    assert not holds_run(kept) and not (kept / "job.json").exists()
    assert main(["train", "--algo", "idqn", *TINY, "--steps", "500", "--out", str(kept)]) == 0  # not "--resume"


def test_a_run_sends_its_rows_and_summary_to_wandb(tmp_path, monkeypatch) -> None:
    """``--logger wandb`` (W&B offline: nothing leaves the machine) gets the rows TensorBoard gets and the final
    summary, in a W&B run inside the run's folder."""
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    out = tmp_path / "run"
    assert main(["train", "--algo", "idqn", *TINY, "--steps", "1000", "--logger", "wandb", "--out", str(out)]) == 0
    logs = list((out / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(logs) == 1
    data = logs[0].read_bytes()
    assert b"eval/return" in data and b"train/loss" in data and b"eval_return" in data  # rows, then the summary


def test_a_run_sends_its_rows_and_summary_to_mlflow(tmp_path, monkeypatch) -> None:
    """``--logger mlflow`` (a local file store: nothing leaves the machine): the run's params, its rows step by step
    and the final summary, read back through MLflow's client."""
    mlflow = pytest.importorskip("mlflow")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", (tmp_path / "mlruns").as_uri())
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")  # MLflow 3 prefers a database; a folder is enough here
    out = tmp_path / "run"
    assert main(["train", "--algo", "idqn", *TINY, "--steps", "1000", "--logger", "mlflow", "--out", str(out)]) == 0
    client = mlflow.tracking.MlflowClient()
    (run,) = client.search_runs([e.experiment_id for e in client.search_experiments()])
    assert run.info.run_name == "run" and run.info.status == "FINISHED"
    assert run.data.params["algo"] == "idqn"
    history = client.get_metric_history(run.info.run_id, "eval.return")
    assert [m.step for m in history] == sorted(m.step for m in history) and history[-1].step >= 1000
    assert "final.eval_return" in run.data.metrics


def test_the_progress_line_tells_the_real_step_count_past_the_budget(capsys) -> None:
    """Every env takes its step, so a run of 3,000 steps on 32 envs ends at 3,008: the progress line read
    ``3,008/3,000 steps``, more done than the whole. Up to the budget it reads N/total; past it the real count and
    why it is more."""
    from convoy.learner.runlog import ProgressDisplay

    row = {"return": 1.0, "loss": 0.1, "epsilon": 0.5, "env_steps_per_s": 1000.0, "updates_per_s": 10.0}
    display = ProgressDisplay(3000, enabled=True)  # output is not a terminal here: one plain line per row
    display.update(2016, row)
    display.update(3008, row)
    display.close()
    first, last = capsys.readouterr().out.splitlines()
    assert first.startswith("2,016/3,000 steps · return 1.00")
    assert last.startswith("3,008 steps (asked 3,000: the last batch step went 8 over) · return 1.00"), last


def test_the_final_evaluation_and_the_references_say_what_they_do(tmp_path, capsys) -> None:
    """A small treadmill run spent ~40 s after its last step (the final evaluation, then the reference drivers and
    planners) with no line. Now a line says the phase began and one more ends each part, with its figure and
    time; the figures are the summary's, the same as ``summary_references`` (the rollouts played one at a time);
    ``--no-progress`` keeps them out."""
    from convoy.envs.treadmill import TreadmillConfig
    from convoy.envs.treadmill.references import summary_references
    from convoy.learner.runlog import EVAL_SEED_OFFSET

    run = ["train", "--inprocess", "--algo", "idqn", "--env", "treadmill", "--steps", "200", "--eval-episodes", "2",
           "--hp", "learning_starts=64", "--hp", "hidden=32"]  # fmt: skip
    assert main([*run, "--out", str(tmp_path / "run")]) == 0
    lines = capsys.readouterr().out.splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("final evaluation: the greedy policy, then"))
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    greedy = f"{summary['eval_return']:.3f} ± {summary['eval_ci95']:.3f}"
    assert lines[at + 1].startswith(f"  greedy policy {greedy} (") and lines[at + 1].endswith(" s)")
    refs = summary["references"]
    shown = lines[at + 2 : at + 2 + len(refs)]
    for k, (line, (name, (mean, ci))) in enumerate(zip(shown, refs.items(), strict=True), 1):
        assert line.startswith(f"  reference {k}/{len(refs)} {name} {mean:.3f} ± {ci:.3f} ("), (line, lines)
    # once a planner is timed, each line says about how long the planners left take
    assert all(line.endswith(" s left)") for line in shown[3:-1]) and not shown[-1].endswith("left)"), shown
    assert "idqn on treadmill" in lines[at + 2 + len(refs)]  # then the summary table
    alone = summary_references(TreadmillConfig(), 2, EVAL_SEED_OFFSET)  # seed 0's evaluation episodes
    assert {k: list(v) for k, v in alone.items()} == refs
    assert main([*run, "--out", str(tmp_path / "quiet"), "--no-progress"]) == 0
    assert "final evaluation" not in capsys.readouterr().out
