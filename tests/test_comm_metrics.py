"""Emergent-communication metrics: estimator identities, shuffled baselines, synthetic rollouts, reports."""

from __future__ import annotations

import math

import numpy as np
import pytest

from convoy.analysis.comm_metrics import (
    MetricFigure,
    cooccurrence_plot,
    entropy,
    instantaneous_coordination,
    message_entropy,
    metrics_table,
    mutual_information,
    per_bit_mi,
    plot_figures,
    shuffled_mi,
    speaker_consistency,
    symbols,
)


def _to_bits(sym: np.ndarray, k: int) -> np.ndarray:
    return ((np.asarray(sym)[..., None] >> np.arange(k)) & 1).astype(np.float32)


# --- estimators ------------------------------------------------------------------------------------------------------


def test_independent_mi_is_near_zero_and_near_shuffled() -> None:
    rng = np.random.default_rng(0)
    x = rng.integers(0, 8, 20_000)
    y = rng.integers(0, 5, 20_000)
    mi = mutual_information(x, y)
    mean, std = shuffled_mi(x, y, np.random.default_rng(1), repeats=20)
    assert 0.0 <= mi < 0.01
    assert 0.0 < mean < 0.01 and std > 0.0
    assert abs(mi - mean) < 5 * std


def test_one_to_one_mapping_mi_equals_entropy() -> None:
    rng = np.random.default_rng(2)
    k = 7
    x = rng.permutation(np.repeat(np.arange(k), 300))  # exact equal counts
    perm = rng.permutation(k) + 100
    y = perm[x]
    assert mutual_information(x, y) == pytest.approx(entropy(x), abs=1e-9)
    assert mutual_information(x, y) == pytest.approx(math.log(k), abs=1e-9)
    skewed = rng.integers(0, 5, 1000) ** 2  # non-uniform, non-contiguous values
    assert mutual_information(skewed, -skewed) == pytest.approx(entropy(skewed), abs=1e-9)


@pytest.mark.parametrize("k", [2, 4, 16])
def test_uniform_entropy_is_log_k(k: int) -> None:
    x = np.random.default_rng(k).permutation(np.repeat(np.arange(k), 50))
    assert entropy(x) == pytest.approx(math.log(k), abs=1e-12)


def test_constant_entropy_is_zero() -> None:
    assert entropy(np.full(100, 3)) == 0.0
    assert mutual_information(np.full(100, 3), np.arange(100)) == 0.0


def test_symbols_pack_and_round_trip() -> None:
    assert symbols(np.array([1, 0, 1, 1])) == 1 + 4 + 8
    assert symbols(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])).tolist() == [0, 1, 2, 3]
    rng = np.random.default_rng(3)
    sym = rng.integers(0, 2**16, size=(5, 6, 7))
    packed = symbols(_to_bits(sym, 16))
    assert packed.dtype == np.int64 and packed.shape == (5, 6, 7)
    np.testing.assert_array_equal(packed, sym)
    big = np.ones(62, dtype=np.int64)
    assert symbols(big) == 2**62 - 1


def test_per_bit_mi_parity_bit() -> None:
    rng = np.random.default_rng(4)
    m = 20_000
    actions = rng.permutation(np.repeat(np.arange(4), m // 4))
    bits = rng.integers(0, 2, size=(m, 5))
    bits[:, 0] = actions % 2
    mi = per_bit_mi(bits, actions)
    assert mi.shape == (5,)
    assert mi[0] == pytest.approx(math.log(2), abs=1e-9)
    assert np.all(mi[1:] < 1e-3)
    for j in range(5):  # agrees with the scalar estimator
        assert mi[j] == pytest.approx(mutual_information(bits[:, j], actions), abs=1e-12)


# --- rollout metrics -------------------------------------------------------------------------------------------------


def test_speaker_consistency_signalling_and_skips_single_action_agents() -> None:
    rng = np.random.default_rng(5)
    m, k, n_actions = 5000, 4, 5
    sym = rng.integers(0, 2**k, size=(m, 3))
    actions = np.stack([sym[:, 0] % n_actions, np.zeros(m, dtype=int), rng.integers(0, n_actions, m)], axis=1)
    bits = _to_bits(sym, k)

    fig = speaker_consistency(bits, actions, np.random.default_rng(6), repeats=10)
    expected = np.mean([mutual_information(sym[:, i], actions[:, i]) for i in (0, 2)])  # agent 1 skipped
    assert fig.value == pytest.approx(expected, abs=1e-12)
    assert fig.key == "speaker_consistency" and fig.unit == "nats" and fig.samples == m
    assert "[1]" in fig.note
    assert (
        fig.shuffled is not None
        and fig.shuffled_std is not None
        and fig.per_bit is not None
        and fig.per_bit_shuffled is not None
    )
    assert fig.value > fig.shuffled + 20 * fig.shuffled_std
    assert fig.per_bit > fig.per_bit_shuffled

    no_info = speaker_consistency(bits, np.zeros((m, 3), dtype=int), np.random.default_rng(7))
    assert no_info.value == 0.0 and no_info.shuffled is None and "no agent" in no_info.note


def _rollout(rng: np.random.Generator, t: int, b: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    sym = rng.integers(0, 2**k, size=(t, b, 2))
    actions = rng.integers(0, 5, size=(t, b, 2))
    return sym, actions


def test_instantaneous_coordination_copying_listener() -> None:
    rng = np.random.default_rng(8)
    sym, actions = _rollout(rng, 50, 100, 3)
    actions[..., 1] = sym[..., 0] % 5  # listener 1 copies speaker 0's symbol
    fig = instantaneous_coordination(_to_bits(sym, 3), actions, np.random.default_rng(9), repeats=10)
    assert fig.samples == 5000 and fig.key == "instantaneous_coordination"
    assert fig.shuffled is not None and fig.shuffled_std is not None
    assert fig.value > fig.shuffled + 20 * fig.shuffled_std
    assert fig.note.startswith("best pair 0→1: ")
    best = float(fig.note.split(": ")[1].split(";")[0])
    assert best == pytest.approx(mutual_information(sym[..., 0].ravel(), actions[..., 1].ravel()), abs=5e-3)

    _, independent = _rollout(rng, 50, 100, 3)
    ind = instantaneous_coordination(_to_bits(sym, 3), independent, np.random.default_rng(10), repeats=20)
    assert (
        ind.shuffled is not None
        and ind.shuffled_std is not None
        and ind.per_bit is not None
        and ind.per_bit_shuffled is not None
    )
    assert abs(ind.value - ind.shuffled) < 5 * ind.shuffled_std
    assert abs(ind.per_bit - ind.per_bit_shuffled) < 2e-3


def test_instantaneous_coordination_delay_pairs_previous_step() -> None:
    rng = np.random.default_rng(11)
    sym, actions = _rollout(rng, 60, 100, 3)
    actions[1:, :, 1] = sym[:-1, :, 0] % 5  # the listener acts on what it heard one step earlier (DIAL)
    bits = _to_bits(sym, 3)
    delayed = instantaneous_coordination(bits, actions, np.random.default_rng(12), repeats=10, delay=1)
    same = instantaneous_coordination(bits, actions, np.random.default_rng(12), repeats=20, delay=0)
    assert delayed.samples == 59 * 100 and delayed.key == "instantaneous_coordination_delay1"
    assert (
        delayed.shuffled is not None
        and delayed.shuffled_std is not None
        and same.shuffled is not None
        and same.shuffled_std is not None
    )
    assert delayed.value > delayed.shuffled + 20 * delayed.shuffled_std
    assert delayed.note.startswith("best pair 0→1")
    assert abs(same.value - same.shuffled) < 5 * same.shuffled_std


def test_message_entropy() -> None:
    m, k = 1024, 3
    sym = np.stack([np.arange(m) % 8, np.zeros(m, dtype=int)], axis=1)
    fig = message_entropy(_to_bits(sym, k))
    assert fig.value == pytest.approx(math.log(8) / 2, abs=1e-12)
    assert fig.per_bit == pytest.approx(math.log(2) / 2, abs=1e-12)
    assert fig.note == f"max {math.log(8):.3f}" and fig.samples == m


# --- reports ---------------------------------------------------------------------------------------------------------


def _figures() -> list[MetricFigure]:
    rng = np.random.default_rng(13)
    sym, actions = _rollout(rng, 20, 50, 4)
    actions[..., 1] = sym[..., 0] % 5
    bits = _to_bits(sym, 4)
    flat_bits, flat_actions = bits.reshape(-1, 2, 4), actions.reshape(-1, 2)
    return [
        speaker_consistency(flat_bits, flat_actions, rng, repeats=5),
        instantaneous_coordination(bits, actions, rng, repeats=5),
        message_entropy(flat_bits),
        MetricFigure("Return with communication", "return", 12.345, "return", note="a | b"),
    ]


def test_metrics_table() -> None:
    figs = _figures()
    table = metrics_table(figs, title="Run 1")
    lines = table.strip().splitlines()
    assert lines[0] == "### Run 1"
    header = (
        "| Emergent Communication Metric Used | Value | shuffled baseline | per bit | per bit (shuffled) | samples"
        " | note |"
    )
    squeezed = [" ".join(line.split()) for line in lines]  # columns are padded to their widest cell
    assert header in squeezed
    rows = lines[squeezed.index(header) + 2 :]
    assert len(rows) == len(figs)
    assert all(f.name in row for f, row in zip(figs, rows, strict=True))
    assert "12.35 return" in rows[-1] and "a \\| b" in rows[-1]
    assert f"{figs[0].value:.3f} nats" in rows[0] and "±" in rows[0]


def test_plots_write_png(tmp_path) -> None:
    out = plot_figures(_figures(), tmp_path / "sub" / "metrics.png", title="metrics")
    assert out.exists() and out.stat().st_size > 1000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rng = np.random.default_rng(14)
    x = rng.integers(0, 2**16, 3000)
    heat = cooccurrence_plot(x, x % 5, tmp_path / "co.png", "message symbol", "action", max_symbols=16)
    assert heat.exists() and heat.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- validation ------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: entropy(np.array([])), "x"),
        (lambda: entropy(np.zeros((3, 2))), "x"),
        (lambda: mutual_information(np.arange(3), np.arange(4)), "x and y"),
        (lambda: mutual_information(np.arange(3), np.array([])), "y"),
        (lambda: shuffled_mi(np.arange(3), np.arange(3), np.random.default_rng(), repeats=0), "repeats"),
        (lambda: symbols(np.zeros((2, 63))), "bits"),
        (lambda: symbols(np.array([0.5, 1.0])), "bits"),
        (lambda: per_bit_mi(np.zeros((4, 2)), np.arange(3)), "bits and y"),
        (lambda: per_bit_mi(np.zeros(4), np.arange(4)), "bits"),
        (lambda: speaker_consistency(np.zeros((4, 2, 3)), np.zeros((4, 3)), np.random.default_rng()), "actions"),
        (lambda: speaker_consistency(np.zeros((4, 3)), np.zeros((4, 3)), np.random.default_rng()), "bits"),
        (lambda: speaker_consistency(np.zeros((0, 2, 3)), np.zeros((0, 2)), np.random.default_rng()), "empty"),
        (lambda: instantaneous_coordination(np.zeros((4, 2, 2, 3)), np.zeros((4, 2)), np.random.default_rng()), "act"),
        (lambda: instantaneous_coordination(np.zeros((4, 2, 1, 3)), np.zeros((4, 2, 1)), np.random.default_rng()), "N"),
        (
            lambda: instantaneous_coordination(
                np.zeros((4, 2, 2, 3)), np.zeros((4, 2, 2)), np.random.default_rng(), delay=4
            ),
            "delay",
        ),
        (lambda: message_entropy(np.zeros((4, 3))), "bits"),
        (lambda: cooccurrence_plot(np.arange(3), np.arange(3), "x.png", "a", "b", max_symbols=0), "max_symbols"),
    ],
)
def test_bad_inputs_raise(call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call()
