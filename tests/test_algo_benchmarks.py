"""The algorithm benchmarks keep running end to end (figures are checked for shape and sanity, never for speed: the
machine is shared)."""

from __future__ import annotations

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch

from convoy.config import MemoryFields

ROOT = Path(__file__).resolve().parents[1]


def run_quick(script: str, *extra: str) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick", *extra],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    return proc


def positive(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def test_inference_scaling_quick_run_writes_table_json_and_plot(tmp_path: Path) -> None:
    out, md, png = tmp_path / "inf.json", tmp_path / "inf.md", tmp_path / "inf.png"
    proc = run_quick("inference_scaling.py", "--json", str(out), "--markdown", str(md), "--plot", str(png))
    assert "| idqn" in proc.stdout and "k (all N)" in proc.stdout
    assert md.read_text().startswith("Inference time per env step")
    assert png.stat().st_size > 1000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    data = json.loads(out.read_text())
    assert data["machine"]["device"] == "cpu"  # where actors act unless runtime.actor_device says otherwise
    assert data["settings"]["agents"] == [2, 4, 8]
    assert data["plot"] == str(png)
    measured = {r["algo"] for r in data["results"]}
    assert "idqn" in measured  # the baseline always exists; the others are picked up when they import
    for r in data["results"]:
        assert r["n_agents"] in (2, 4, 8) and r["batch"] == 1
        assert positive(r["ms_per_act"]["median"]) and positive(r["ms_per_act"]["best"])
        assert positive(r["params"]) and positive(r["flops_per_act"])
    assert set(data["fits"]) == measured
    for f in data["fits"].values():
        assert f["agents"] == [2, 4, 8] and f["upper_agents"] == [4, 8]
        for key in ("exponent_all", "exponent_upper", "flops_exponent_all", "flops_exponent_upper"):
            assert isinstance(f[key], float) and math.isfinite(f[key])
        assert f["flops_exponent_all"] > 0.5  # more agents, more work: a counting bug would show here
    for note in data["notes"]:
        assert isinstance(note, str)


def test_learner_throughput_quick_run_reports_rates_flops_and_peak(tmp_path: Path) -> None:
    out, md = tmp_path / "lt.json", tmp_path / "lt.md"
    proc = run_quick("learner_throughput.py", "--dial-envs", "4", "--json", str(out), "--markdown", str(md))
    assert "| idqn" in proc.stdout and "of peak" in proc.stdout
    assert "Target ≥ 0.5" in md.read_text()

    data = json.loads(out.read_text())
    assert positive(data["peak"]["gflops"]) and data["peak"]["op"] == "torch.mm float32"
    assert positive(data["memory_read_gbs"])  # the roofline's other side, measured in the same run
    expected = "cuda" if torch.cuda.is_available() else "cpu"  # --device auto, as the learner's JobConfig.device
    assert data["machine"]["device"] == data["peak"]["device"] == expected
    assert data["target_fraction"] == 0.5
    measured = {r["algo"] for r in data["results"]}
    assert "idqn" in measured
    for r in data["results"]:
        for key in ("updates_per_s", "transitions_per_s", "flops_per_update", "gflops_per_s", "fraction_of_peak"):
            assert positive(r[key]), (r["algo"], key, r[key])
        assert positive(r["ms_per_update"]["median"]) and positive(r["transitions_per_update"])
        assert math.isclose(r["transitions_per_s"], r["transitions_per_update"] * r["updates_per_s"], rel_tol=1e-9)
        assert sum(r["flops_by_op"].values()) == r["flops_per_update"]
        g = r["gemms_alone"]  # the FLOPs replayed are the FLOPs torch counted in the update
        assert g["count"] > 0 and g["flops"] == r["flops_per_update"]
        assert positive(g["warm_s"]) and positive(g["cold_s"]) and positive(r["gemms_in_update_s"])
        if r["chunk_len"] > 1:  # DIAL: one update = one chunk of --dial-envs sequences
            assert r["transitions_per_update"] == 4 * r["chunk_len"]
        else:
            assert r["transitions_per_update"] == r["batch_size"] == 32
    # the memory modules' LSTMs are counted (a fused kernel torch's own counter sees as 0 FLOPs): forward and backward
    # of a window × 128-unit layer over every agent's row, at least 3 · 2 · rows · window · H · 4H beyond their base
    flops = {r["algo"]: r["flops_per_update"] for r in data["results"]}
    window, units = MemoryFields().memory_window, MemoryFields().memory_hidden
    lstm_min = 3 * 2 * (32 * data["settings"]["n_agents"]) * window * units * 4 * units
    for base in ("ma-mesn", "ma-bon"):
        assert flops[f"{base}-mm"] - flops[base] >= lstm_min, (base, flops)


def load_benchmark(name: str) -> Any:
    """A benchmark script as a module (they are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_gemm_clock_times_the_gemms_inside_a_step_and_judges_the_budget() -> None:
    """The in-update GEMM timer counts the matmuls a step runs and nothing else; ``gemm_bound`` compares their time
    with what an update at the target fraction may take."""
    lt = load_benchmark("learner_throughput")
    torch.manual_seed(0)
    x, w1, w2 = torch.randn(8, 5), torch.randn(5, 16), torch.randn(16, 3)
    with lt.GemmClock(torch.device("cpu")) as clock:
        h = torch.relu(x @ w1)
        torch.addmm(torch.zeros(3), h, w2).exp()  # relu, zeros, exp: not GEMMs, not timed
    assert clock.calls == 2 and clock.seconds > 0
    assert lt.is_gemm(torch.ops.aten.bmm.default) and not lt.is_gemm(torch.ops.aten.relu.default)

    case = type("C", (), {"flops": 10**9, "gemms_in_update_s": 0.021})()
    assert lt.gemm_bound(case, peak=100.0)  # 1 GFLOP at 0.5 of 100 GFLOP/s may take 20 ms
    case.gemms_in_update_s = 0.019
    assert not lt.gemm_bound(case, peak=100.0)


@pytest.mark.filterwarnings("ignore:TF32 acceleration on top of oneDNN")  # mkldnn.flags() on a build without XPU
def test_fused_lstm_flops_equal_the_same_layers_run_step_by_step() -> None:
    """``benchmarks/flops.py``'s formulas for the fused RNN kernels count what torch counts for the unfused path."""
    bench_flops = load_benchmark("flops")
    torch.manual_seed(0)
    lstm = torch.nn.LSTM(27, 64, num_layers=2, batch_first=True)
    x = torch.randn(5, 8, 27, requires_grad=True)
    h0, c0 = torch.zeros(2, 5, 64, requires_grad=True), torch.zeros(2, 5, 64, requires_grad=True)

    def forward() -> None:
        lstm(x, (h0, c0))[0].sum()

    def train_step() -> None:
        lstm(x, (h0, c0))[0].sum().backward()

    if not torch.backends.mkldnn.is_available():
        pytest.skip("this torch build has no oneDNN: its LSTM is never fused on CPU")
    counted, fused_ops = {}, set()
    for fused in (True, False):
        with torch.backends.mkldnn.flags(enabled=fused):
            (fwd, by_op), (step, by_op_step) = bench_flops.count_flops(forward), bench_flops.count_flops(train_step)
        counted[fused] = (fwd, step)
        if fused:
            fused_ops = set(by_op) | set(by_op_step)
    assert {"aten.mkldnn_rnn_layer", "aten.mkldnn_rnn_layer_backward"} <= fused_ops  # the fused kernels did run
    per_layer = 2 * 5 * 8 * 4 * 64  # 2 · rows · 4H
    assert counted[False][0] == per_layer * (27 + 64) + per_layer * (64 + 64)
    assert counted[True] == counted[False]
    assert counted[False][1] == 3 * counted[False][0]


def test_decentralized_quick_run_reports_every_method_and_the_channel_table(tmp_path: Path) -> None:
    out, png = tmp_path / "dec.json", tmp_path / "dec.png"
    proc = run_quick("decentralized.py", "--seeds", "0", "--json", str(out), "--plot", str(png), "--out", str(tmp_path))
    assert "MA-MeSN-MM (no channel)" in proc.stdout and "Channel robustness" in proc.stdout
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    data = json.loads(out.read_text())
    assert {r["method"] for r in data["runs"]} == {"ma-mesn-mm", "idqn", "dqn-ser", "codbc"}
    codbc = next(r for r in data["runs"] if r["method"] == "codbc")
    assert codbc["total_env_steps"] == 2 * data["settings"]["steps"]  # it needs its teacher's run first
    assert all(math.isfinite(r["final_return"]) and r["curve"] for r in data["runs"])
    drops = sorted({(r["drop"], r["method"]) for r in data["channel"]})
    assert drops == [(d, m) for d in (0.0, 0.5, 1.0) for m in ("ma-mesn", "ma-mesn-mm")]
    zero = {r["method"]: r["return"] for r in data["channel"] if r["drop"] == 0.0}
    assert zero["ma-mesn"] == zero["ma-mesn-mm"]  # nothing is lost at drop 0: the same policy, the same episodes
    assert (tmp_path / "ma-mesn-mm-0" / "checkpoint.pt").is_file()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
@pytest.mark.parametrize("script", ["learner_throughput.py", "inference_scaling.py"])
def test_benchmarks_refuse_cuda_where_there_is_none_and_say_what_to_pick(script: str) -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick", "--device", "cuda"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert proc.returncode == 2
    assert "--device cuda: torch sees no CUDA device here; use --device auto" in proc.stderr


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_learner_throughput_runs_on_cuda(tmp_path: Path) -> None:
    out = tmp_path / "lt.json"
    run_quick("learner_throughput.py", "--device", "cuda", "--algos", "idqn", "ma-bon", "--json", str(out))
    data = json.loads(out.read_text())
    assert data["machine"]["device"] == data["peak"]["device"] == "cuda"
    assert positive(data["peak"]["gflops"]) and positive(data["memory_read_gbs"])
    for r in data["results"]:
        assert positive(r["fraction_of_peak"]) and r["gemms_alone"]["flops"] == r["flops_per_update"]
