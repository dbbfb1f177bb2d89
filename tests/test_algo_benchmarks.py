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


def load_benchmark(name: str) -> Any:
    """A benchmark script as a module (they are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_inference_flops_count_a_fused_lstm_as_the_matmuls_it_is_made_of() -> None:
    """The memory modules' ``nn.LSTM`` runs as one oneDNN kernel that torch's ``FlopCounterMode`` counts as 0 FLOPs;
    ``inference_scaling.count_flops`` counts the same layer's matmuls: 2 · rows · 4H · (in + H) per layer forward,
    twice that backward."""
    inference = load_benchmark("inference_scaling")
    torch.manual_seed(0)
    lstm = torch.nn.LSTM(27, 64, num_layers=2, batch_first=True)
    x = torch.randn(5, 8, 27, requires_grad=True)
    h0, c0 = torch.zeros(2, 5, 64, requires_grad=True), torch.zeros(2, 5, 64, requires_grad=True)

    def forward() -> None:
        lstm(x, (h0, c0))[0].sum()

    def train_step() -> None:
        lstm(x, (h0, c0))[0].sum().backward()

    per_layer = 2 * 5 * 8 * 4 * 64  # 2 · rows · 4H
    forward_flops = per_layer * (27 + 64) + per_layer * (64 + 64)
    assert inference.count_flops(forward) == forward_flops
    assert inference.count_flops(train_step) == 3 * forward_flops
    lstm(x)  # counting leaves oneDNN as it was
    assert (
        torch.backends.mkldnn.is_available() == torch._C._get_mkldnn_enabled()
        or not torch.backends.mkldnn.is_available()
    )


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
def test_inference_scaling_refuses_cuda_where_there_is_none_and_says_what_to_pick() -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "inference_scaling.py"), "--quick", "--device", "cuda"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=ROOT,
    )
    assert proc.returncode == 2
    assert "--device cuda: torch sees no CUDA device here; use --device auto" in proc.stderr
