"""The benchmark scripts keep running (figures are printed, never asserted: the machine is shared)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_env_throughput_quick_run_reports_every_case(tmp_path) -> None:
    out = tmp_path / "bench.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "env_throughput.py"), "--quick", "--skip-highway",
         "--batch-sizes", "1", "64", "--agents", "2", "4", "--adapter-envs", "0", "--json", str(out)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "| treadmill" in proc.stdout and "agent-steps/s" in proc.stdout
    data = json.loads(out.read_text())
    assert data  # figures were written


def test_speaker_listener_quick_run_reports_every_variant_and_the_bounds(tmp_path) -> None:
    out, png = tmp_path / "sl.json", tmp_path / "sl.png"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "speaker_listener.py"), "--quick", "--json", str(out),
         "--plot", str(png)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "target ma-mesn better than" in proc.stdout and "target ma-mesn+ps better than" in proc.stdout
    data = json.loads(out.read_text())
    assert set(data["summary"]) == {"ma-mesn", "ma-mesn+ps", "idqn"} and png.stat().st_size > 10_000


def test_treadmill_learning_tiny_run_reports_variants_references_and_analysis(tmp_path) -> None:
    """A full-information learner is a variant of a run (its job trains on full_information observations); --set
    changes a treadmill rule for every run."""
    out = tmp_path / "tl.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "treadmill_learning.py"), "--algos", "ma-mesn",
         "idqn+full-information", "--seeds", "0", "--steps", "1500", "--eval-every", "1000", "--episodes", "8",
         "--eval-episodes", "4", "--analyze", "ma-mesn", "--analysis-samples", "256", "--set", "observe_k=2", "--out",
         str(tmp_path / "runs"), "--json", str(out)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out.read_text())
    assert {"ma-mesn", "idqn+full-information", "random", "scripted"} <= set(data["summary"])
    assert "message_entropy" in data["summary"]["ma-mesn"]["analysis"]
    full = next(r for r in data["runs"] if r["algo"] == "idqn+full-information")
    header = Path(full["out"]).with_suffix(".log").read_text().splitlines()[0]
    assert header.startswith("idqn on treadmill {") and "best_held_out" in full
    assert "'full_information': True" in header and "'observe_k': 2" in header  # the variant and --set both reach it
    log = tmp_path / "runs" / "ma-mesn-s0.log"
    trained_at = log.stat().st_mtime_ns
    again = subprocess.run(  # --reuse keeps the finished runs: nothing trains, the figures are the same
        [sys.executable, str(ROOT / "benchmarks" / "treadmill_learning.py"), "--algos", "ma-mesn", "--seeds", "0",
         "--steps", "1500", "--episodes", "8", "--analyze", "--analysis-samples", "256", "--out",
         str(tmp_path / "runs"), "--reuse"],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    assert log.stat().st_mtime_ns == trained_at
    mesn = next(r for r in data["runs"] if r["algo"] == "ma-mesn")
    assert f"final {mesn['eval_return']:.1f}" in again.stdout
    bad = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "treadmill_learning.py"), "--algos", "idqn+oracle"],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip
    assert bad.returncode != 0 and "unknown variant 'oracle'" in bad.stderr


def test_updates_quick_run_times_every_algorithm_beside_the_reference(tmp_path) -> None:
    out = tmp_path / "updates.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "updates.py"), "--quick", "--algos", "idqn", "dial", "ma-mesn",
         "--json", str(out)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Convoy ÷ reference" in proc.stdout and "| dial" in proc.stdout
    (size,) = json.loads(out.read_text()).values()
    assert set(size) == {"idqn", "dial", "ma-mesn"}
    for name, f in size.items():
        assert f["convoy_ms"] > 0 and f["reference_ms"] > 0, name
        assert f["convoy_over_reference"] == f["convoy_ms"] / f["reference_ms"]
    assert size["idqn"]["rows_per_update"] == size["ma-mesn"]["rows_per_update"] == 32 * 3  # batch × agents
    assert size["dial"]["rows_per_update"] == 32 * 8 * 3  # DIAL samples sequences of 8 steps


def test_the_reference_update_minimises_the_loss_convoys_independent_dqn_does() -> None:
    """The benchmark compares like with like: given Convoy's weights and batch, the plain ``nn.Sequential`` reference
    computes the loss Convoy's IDQN update reports (double Q, advantage-learning gap, Huber, summed over agents)."""
    import importlib.util

    import torch

    spec = importlib.util.spec_from_file_location("bench_updates", ROOT / "benchmarks" / "updates.py")
    assert spec is not None and spec.loader is not None
    updates = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(updates)
    hidden = (32, 16)
    algo = updates.filled("idqn", hidden=hidden, batch_size=16)
    ref = updates.reference_for(algo, hidden)

    def copy(seq: torch.nn.Sequential, mlp: torch.nn.Module) -> None:
        from convoy.algos.nets import GroupLinear

        linears = [m for m in seq if isinstance(m, torch.nn.Linear)]
        layers = [m for m in mlp.modules() if isinstance(m, GroupLinear)]  # the MLP's layers, in order
        with torch.no_grad():
            for linear, layer in zip(linears, layers, strict=True):
                linear.weight.copy_(layer.weight[0, 0].T)  # run 0's, group 0's
                linear.bias.copy_(layer.bias[0, 0])

    for _ in range(3):  # the online network moves away from the target: the double-Q argmax matters
        algo.update()
    copy(ref.q, algo.online["q"])
    copy(ref.target, algo.target["q"])
    batch = algo.sample()
    with torch.no_grad():
        expected = float(ref.loss({k: v[0] for k, v in batch.columns().items()}))  # the run's (a run of one)
    algo.sample = lambda: batch
    assert abs(algo.update().read()[0]["loss"] - expected) <= 1e-5 * max(1.0, abs(expected))


@pytest.mark.slow  # compiles two graphs (Inductor, C++): ~1 min on 2 cores
def test_gpu_benchmark_quick_run_times_eager_and_captured_updates_and_training(tmp_path) -> None:
    """``benchmarks/gpu.py`` on the CPU (what runs it wherever a GPU is lent is the same code on ``--device cuda``)."""
    out = tmp_path / "gpu.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "gpu.py"), "--device", "cpu", "--quick", "--json", str(out)],
        capture_output=True, text=True, timeout=900, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "captured IDQN update at P = 1" in proc.stdout and "one CPU core" in proc.stdout
    data = json.loads(out.read_text())
    for size in ("1", "2"):
        f = data["updates"]["idqn"][size]
        assert f["eager_ms"] > 0 and f["captured_ms"] > 0 and f["cudagraph_skips"] == 0
        assert 0 < f["sample_ms"] < f["eager_ms"]  # the draw is a part of the eager update
    assert data["training"]["2"]["steps_per_s"] > 0 and data["training"]["cpu_core_steps_per_s"] > 0


def test_treadmill_imitation_clones_the_planner_into_the_learners_network(tmp_path) -> None:
    """DAgger labels every state the student reaches with the teacher's action; each seed's clone fits those labels
    far above chance (1 in 9), is scored on held-out episodes beside its teacher, and --learn Q-learns on from it."""
    out = tmp_path / "imitation.json"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "treadmill_imitation.py"), "--rounds", "2", "--episodes", "8",
         "--eval-episodes", "4", "--epochs", "3", "--seeds", "0", "1", "--learn", "1500", "--hp",
         "learning_starts=200", "--out", str(tmp_path / "learn"), "--json", str(out)],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    data = json.loads(out.read_text())
    first, second = data["rounds"]
    assert first["beta"] == 1.0 and second["beta"] == 0.5 and second["states"] > first["states"]
    assert second["train_accuracy"] > 0.4
    assert data["teacher"] == "private-planner" and data["job"]["preset"] == "charger"
    assert second["of_teacher"] == pytest.approx(second["mean"] / data["teacher_held_out"])
    assert len(second["held_out"]) == 2 and len(data["learned"]["held_out"]) == 2  # one clone per seed
    for seed in (0, 1):  # then Q-learning went on from them as convoy train's runs
        assert (tmp_path / "learn" / f"seed-{seed}" / "checkpoint.pt").is_file()
    clone_only = subprocess.run(  # without --learn: the clones alone
        [sys.executable, str(ROOT / "benchmarks" / "treadmill_imitation.py"), "--rounds", "1", "--episodes", "4",
         "--eval-episodes", "2", "--epochs", "1", "--json", str(out)],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )  # fmt: skip
    assert clone_only.returncode == 0, clone_only.stderr
    assert "learned" not in json.loads(out.read_text())
