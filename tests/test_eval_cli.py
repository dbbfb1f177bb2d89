"""``convoy eval`` and ``convoy analyze`` on checkpoints of real (tiny) training runs.

What a user relies on: the figures are printed and written where asked, every message probe (predicted, noise,
a lossy channel) runs end to end through the CLI, the analysis writes its table and plots, and every kind of bad
input — a missing, corrupt, truncated or foreign file, a bad channel spec, a probe the algorithm cannot do — is one
readable line on stderr with exit code 2, never a traceback, and never touches the checkpoint it was given.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch
from PIL import Image
from PIL.GifImagePlugin import GifImageFile

from convoy.cli.main import main
from convoy.config import job_config
from convoy.services.training import run_inprocess

GLIMPSE = {"n_targets": 4, "rounds": 2, "listener_glimpse": True}
SMALL_TREADMILL = {"n_agents": 2, "n_adversaries": 1, "length": 30, "width": 12, "max_steps": 50}
EPISODES = ["--episodes", "20", "--device", "cpu"]


def train(out: Path, algo: str, env: str, env_params: dict[str, Any], steps: int, **algo_params: Any) -> Path:
    """A tiny in-process run on CPU; returns its checkpoint."""
    job = job_config(
        algo=algo,
        env=env,
        env_params=env_params,
        algo_params={"hidden": (16,), "learning_starts": 64, **algo_params},
        steps=steps,
        num_envs=32,
        seed=0,
        eval_episodes=0,
        device="cpu",
    )
    before = torch.get_num_threads()
    try:
        run_inprocess(job, out_dir=out, progress=False)
    finally:
        torch.set_num_threads(before)
    return out / "checkpoint.pt"


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Checkpoints of tiny runs: the memory-module model the tests probe, plus the algorithms that refuse probes."""
    root = tmp_path_factory.mktemp("ckpts")
    torch.set_num_threads(1)
    mm = {"memory_window": 2, "memory_hidden": 8}
    return {
        "mm": train(root / "mm", "ma-mesn-mm", "referential", GLIMPSE, 2000, **mm),
        "mesn": train(root / "mesn", "ma-mesn", "referential", GLIMPSE, 300),
        "idqn": train(root / "idqn", "idqn", "referential", GLIMPSE, 300),
    }


def snapshot(paths: dict[str, Path]) -> dict[str, tuple[bytes, int]]:
    return {k: (p.read_bytes(), p.stat().st_mtime_ns) for k, p in paths.items()}


def flat(text: str) -> str:
    return " ".join(text.split())


def wrote(path: Path, text: str) -> bool:
    """Whether the console said it wrote ``path`` (its wrapping may cut a long tmp path mid-name)."""
    return f"wrote{path}" in "".join(text.split())


# --------------------------------------------------------------------------- convoy eval


def test_eval_prints_the_greedy_return_with_its_ci(ckpts: dict[str, Path], capsys: pytest.CaptureFixture) -> None:
    assert main(["eval", str(ckpts["mm"]), *EPISODES]) == 0
    out = flat(capsys.readouterr().out)
    assert "greedy return" in out and "95 % CI" in out and "20 episodes" in out and "messages: sent" in out
    assert "random policy" in out and "ma-mesn-mm on referential" in out


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--messages", "predicted"], "messages: predicted"),
        (["--messages", "noise"], "messages: noise"),
        (["--channel", "drop=0.3,flip=0.01"], "messages: sent through channel drop=0.3,flip=0.01"),
        (["--channel", "drop=0.5,latency=1"], "through channel drop=0.5,latency=1"),
    ],
    ids=["predicted", "noise", "drop-flip", "drop-latency"],
)
def test_eval_message_probes(
    flags: list[str], needle: str, ckpts: dict[str, Path], capsys: pytest.CaptureFixture
) -> None:
    assert main(["eval", str(ckpts["mm"]), *EPISODES, *flags]) == 0
    out = flat(capsys.readouterr().out)
    assert "greedy return" in out and needle in out


def test_a_probe_prints_the_true_return_and_the_paired_difference(
    ckpts: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """``--messages shuffled`` printed only the shuffled return, when the question it answers is whether the
    messages matter: now also the true messages' return on the same episodes and the paired difference with its CI,
    beside the probe's return; ``--json`` keeps both."""
    import numpy as np

    from convoy.stats import ci95_half

    probe, plain = tmp_path / "probe.json", tmp_path / "plain.json"
    assert main(["eval", str(ckpts["mm"]), *EPISODES, "--messages", "shuffled", "--json", str(probe)]) == 0
    out = capsys.readouterr().out
    true_line = next(line for line in out.splitlines() if line.startswith("true messages:"))
    probe_line = flat(out).split("greedy return: ")[1].split("random policy:")[0]
    assert "messages: sent" in true_line and "20 episodes" in true_line, out
    assert "messages: shuffled" in probe_line and "paired vs true messages" in probe_line, out
    data = json.loads(probe.read_text())
    diff = np.array(data["returns"]) - np.array(data["true_returns"])
    assert data["paired_difference"] == pytest.approx(diff.mean()) and data["paired_ci95"] == pytest.approx(
        ci95_half(diff, single=0.0)
    )
    assert f"{diff.mean():+.3f} ± {ci95_half(diff, single=0.0):.3f}" in probe_line, probe_line
    assert main(["eval", str(ckpts["mm"]), *EPISODES, "--json", str(plain)]) == 0  # the true messages alone
    alone = capsys.readouterr().out
    assert "paired" not in alone and "true messages:" not in alone, alone
    assert json.loads(plain.read_text())["returns"] == data["true_returns"]  # the same episodes: paired
    assert "true_returns" not in json.loads(plain.read_text())


def test_eval_writes_json(ckpts: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "sub" / "out.json"
    assert main(["eval", str(ckpts["mm"]), *EPISODES, "--messages", "noise", "--json", str(path)]) == 0
    assert wrote(path, capsys.readouterr().out)
    data = json.loads(path.read_text())
    assert data["algo"] == "ma-mesn-mm" and data["env"] == "referential" and data["messages"] == "noise"
    assert data["episodes"] == 20 and len(data["returns"]) == 20
    assert set(data["returns"]) <= {0.0, 1.0}  # the referential game pays 1 for a hit, else 0
    assert data["mean_return"] == pytest.approx(sum(data["returns"]) / 20)
    assert data["ci95"] >= 0.0 and 0.0 <= data["random_return"] <= 1.0


def test_eval_is_reproducible(ckpts: dict[str, Path], tmp_path: Path) -> None:
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    for path in (a, b):
        assert main(["eval", str(ckpts["mm"]), *EPISODES, "--channel", "drop=0.5", "--json", str(path)]) == 0
    assert json.loads(a.read_text())["returns"] == json.loads(b.read_text())["returns"]


@pytest.mark.parametrize(
    ("command", "mentions"),
    [("eval", ["--channel", "--messages", "drop=0.3,flip=0.01"]), ("analyze", ["--samples", "--repeats", "--out"])],
)
def test_help_mentions_the_options(command: str, mentions: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_:
        main([command, "--help"])
    assert exit_.value.code == 0
    out = flat(capsys.readouterr().out)
    assert all(word in out for word in mentions), out


# --------------------------------------------------------------------------- convoy analyze


def test_analyze_writes_table_and_plots(ckpts: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out_dir = tmp_path / "analysis"
    argv = ["analyze", str(ckpts["mm"]), "--samples", "2000", "--episodes", "20", "--repeats", "3"]
    assert main([*argv, "--out", str(out_dir), "--device", "cpu"]) == 0
    out = capsys.readouterr().out
    assert "|" in out and "Instantaneous coordination" in out and "shuffled baseline" in out
    assert "predicted messages" in out  # a memory-module model also reports its no-channel return
    for name in ("table.md", "analysis.json", "metrics.png", "cooccurrence.png"):
        assert (out_dir / name).stat().st_size > 0, name
    assert "Instantaneous coordination" in (out_dir / "table.md").read_text()
    data = json.loads((out_dir / "analysis.json").read_text())
    keys = {f["key"] for f in data["figures"]}
    assert {"return_sent", "return_noise", "return_predicted", "message_input_norm", "causal_influence"} <= keys
    for png in ("metrics.png", "cooccurrence.png"):
        with Image.open(out_dir / png) as img:
            assert img.format == "PNG" and img.size[0] > 100


# --------------------------------------------------------------------------- bad input


def bad_files(ckpts: dict[str, Path], tmp: Path) -> dict[str, Path]:
    """Files that are not usable checkpoints, made next to (never from a write to) the real one."""
    real = ckpts["mm"].read_bytes()
    noise = tmp / "noise.pt"
    noise.write_bytes(
        torch.randint(0, 256, (4096,), generator=torch.Generator().manual_seed(0)).byte().numpy().tobytes()
    )
    truncated = tmp / "truncated.pt"
    truncated.write_bytes(real[: len(real) // 2])
    foreign = tmp / "foreign.pt"
    torch.save({"model": {"w": torch.zeros(3)}, "epoch": 3}, foreign)
    return {"noise": noise, "truncated": truncated, "foreign": foreign, "missing": tmp / "nope" / "checkpoint.pt"}


BAD_INPUTS = [
    ("missing", ["eval", "{missing}"], "no such file"),
    ("noise", ["eval", "{noise}"], "cannot be read"),
    ("truncated", ["eval", "{truncated}"], "cannot be read"),
    ("foreign", ["eval", "{foreign}"], "not a Convoy checkpoint"),
    ("missing-analyze", ["analyze", "{missing}"], "no such file"),
    ("truncated-analyze", ["analyze", "{truncated}"], "cannot be read"),
    ("drop=2", ["eval", "{mm}", "--channel", "drop=2"], "channel: drop"),
    ("nonsense", ["eval", "{mm}", "--channel", "nonsense"], "channel: "),
    ("bogus-key", ["eval", "{mm}", "--channel", "bogus=1"], "bogus"),
    ("channel+predicted", ["eval", "{mm}", "--channel", "drop=0.1", "--messages", "predicted"], "channel: "),
    ("predicted-no-memory", ["eval", "{mesn}", "--messages", "predicted"], "train ma-mesn-mm or ma-bon-mm"),
    ("noise-no-messages", ["eval", "{idqn}", "--messages", "noise"], "messages: "),
    ("gif-not-treadmill", ["eval", "{mm}", "--gif", "{tmp}/x.gif"], "--gif: only the treadmill"),
    ("episodes=0", ["eval", "{mm}", "--episodes", "0"], "--episodes: must be ≥ 1"),
    ("analyze-samples=0", ["analyze", "{mm}", "--samples", "0"], "--samples: must be ≥ 1"),
    ("analyze-idqn", ["analyze", "{idqn}", "--samples", "100", "--episodes", "4"], "sends no discrete"),
]


@pytest.mark.parametrize(("case", "argv", "needle"), BAD_INPUTS, ids=[c[0] for c in BAD_INPUTS])
def test_bad_input_is_one_line_and_exit_2(
    case: str, argv: list[str], needle: str, ckpts: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    paths = {**{k: str(v) for k, v in {**ckpts, **bad_files(ckpts, tmp_path)}.items()}, "tmp": str(tmp_path)}
    before = snapshot(ckpts)
    code = main([a.format(**paths) for a in argv] + ["--device", "cpu"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error:"), err
    assert needle in lines[0], err
    assert snapshot(ckpts) == before  # corrupt input loses nothing
    assert not (tmp_path / "x.gif").exists()


def test_analyze_repeats_zero_is_one_line(
    ckpts: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    argv = ["analyze", str(ckpts["mm"]), "--samples", "100", "--episodes", "4", "--repeats", "0"]
    assert main([*argv, "--out", str(tmp_path), "--device", "cpu"]) == 2
    assert "--repeats" in capsys.readouterr().err


# --------------------------------------------------------------------------- the treadmill GIF


def test_eval_gif_on_the_treadmill(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    ckpt = train(tmp_path / "run", "ma-mesn", "treadmill", SMALL_TREADMILL, 500, message_bits=4)
    gif = tmp_path / "out" / "episode.gif"
    assert main(["eval", str(ckpt), "--episodes", "4", "--gif", str(gif), "--device", "cpu"]) == 0
    out = flat(capsys.readouterr().out)
    assert "greedy return" in out and wrote(gif, out)
    assert gif.stat().st_size > 0
    with Image.open(gif) as img:
        assert isinstance(img, GifImageFile) and img.format == "GIF" and img.n_frames > 1


# --------------------------------------------------------------------------- hostile checkpoints


class _Touch:
    """Unpickling this runs ``open(path, "w")``: what a hostile "checkpoint" does under a full pickle load."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (str(self.path), "w"))


def test_a_hostile_checkpoint_runs_no_code(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A pickle whose loading creates a file: the old loader (``weights_only=False``) runs it, ``convoy eval`` and a
    CoDBC teacher refuse it with a clear error, and the file never appears."""
    from convoy.algos.checkpoint import CheckpointError, read_checkpoint
    from convoy.config import resolve_algo
    from convoy.validation import ConfigError

    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({"kind": "convoy-checkpoint", "format": 1, "state": _Touch(marker)}, evil)
    torch.load(evil, weights_only=False)  # the old loader: the file's code runs
    assert marker.exists()
    marker.unlink()

    assert main(["eval", str(evil), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "refused" in err and "could run code" in err, err
    with pytest.raises(CheckpointError, match="refused"):
        read_checkpoint(evil)
    from convoy.algos.codbc import CoDBC
    from convoy.algos.registry import make_algorithm
    from convoy.envs import make_batched

    env = make_batched("treadmill", 2, n_agents=2, n_adversaries=1)
    cfg = resolve_algo("codbc", "treadmill", {"teacher": str(evil), "hidden": (16,)})
    student = make_algorithm("codbc", env.spec, cfg, device="cpu", seed=0)
    assert isinstance(student, CoDBC)
    with pytest.raises(ConfigError, match="refused") as info:
        student.teacher  # noqa: B018 (loaded on first use)
    assert info.value.field == "teacher"
    assert not marker.exists()
