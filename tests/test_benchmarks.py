"""The benchmark scripts keep running (figures are printed, never asserted: the machine is shared)."""

import json
import subprocess
import sys
from pathlib import Path

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


def test_speaker_listener_quick_run_reports_both_algorithms_and_bounds(tmp_path) -> None:
    out, png = tmp_path / "sl.json", tmp_path / "sl.png"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "speaker_listener.py"), "--quick", "--json", str(out),
         "--plot", str(png)],
        capture_output=True, text=True, timeout=300, cwd=ROOT,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "target MA-MeSN better than" in proc.stdout
    data = json.loads(out.read_text())
    assert set(data["summary"]) == {"ma-mesn", "idqn"} and png.stat().st_size > 10_000
