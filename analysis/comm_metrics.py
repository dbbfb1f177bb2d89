"""Emergent-communication metrics after Lowe et al. 2019, "On the pitfalls of measuring emergent communication".

The paper's point is that a single number such as "speaker consistency = 1.2 nats" says little on its own: plug-in
mutual-information estimates are biased upwards, and the bias grows with the vocabulary and shrinks with the sample
count. So every MI figure here comes with

* a **shuffled-pairs baseline**: the same estimator applied after permuting one side of the pairing, which keeps both
  marginals (and hence the bias) and destroys the dependence. A figure is only meaningful well above it;
* a **per-bit** figure: MI between each message bit and the action. A bit is a 2-symbol vocabulary, so its plug-in
  bias is tiny even when the full message (up to 2**k symbols) is badly under-sampled.

Choices:

* Messages are binary vectors packed into int64 symbols (bit j has weight 2**j), so k ≤ 62 keeps them exact.
* Estimates are plug-in (maximum-likelihood) entropies in nats from co-occurrence counts: unbiased corrections
  (Miller-Madow, NSB) assume things about the unseen symbols; the shuffled baseline measures the bias instead.
* Everything is vectorised: values are mapped to dense codes with ``np.unique(return_inverse=True)``, pairs to one
  joint code, and counted with ``np.bincount``. Python loops run only over agents, pairs and shuffle repeats.
* Agents (or listeners) with a single action are skipped: their action carries no information, and averaging their
  zeros in would dilute the figure for the agents that do act.
* Plotting uses matplotlib's Agg backend, imported lazily, so the metrics work headless and without a display.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from convoy.output import markdown_table, pyplot, save_figure

__all__ = [
    "MetricFigure",
    "cooccurrence_plot",
    "entropy",
    "instantaneous_coordination",
    "message_entropy",
    "metrics_table",
    "mutual_information",
    "per_bit_mi",
    "plot_figures",
    "shuffled_mi",
    "speaker_consistency",
    "symbols",
]

MAX_BITS = 62
_BINCOUNT_LIMIT = 1 << 22  # joint tables larger than this are counted with np.unique instead of a dense bincount


# ---------------------------------------------------------------------------------------------------------------------
# validation and counting helpers


def _as_1d(x: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty")
    return arr


def _paired(x: np.ndarray, y: np.ndarray, xname: str = "x", yname: str = "y") -> tuple[np.ndarray, np.ndarray]:
    xa, ya = _as_1d(x, xname), _as_1d(y, yname)
    if len(xa) != len(ya):
        raise ValueError(f"{xname} and {yname} must have the same length, got {len(xa)} and {len(ya)}")
    return xa, ya


def _codes(x: np.ndarray) -> tuple[np.ndarray, int]:
    """Dense codes 0..n-1 for the distinct values of x, so joint codes stay small enough to bincount."""
    uniq, inv = np.unique(x, return_inverse=True)
    return inv.reshape(-1).astype(np.int64), len(uniq)


def _h_counts(counts: np.ndarray) -> np.ndarray:
    """Plug-in entropy (nats) of count tables along the last axis: ln n − Σ c ln c / n."""
    c = np.asarray(counts, dtype=np.float64)
    n = c.sum(axis=-1)
    clogc = np.where(c > 0, c * np.log(np.where(c > 0, c, 1.0)), 0.0).sum(axis=-1)
    return np.log(n) - clogc / n


def _joint_counts(ix: np.ndarray, iy: np.ndarray, ny: int, nx: int) -> np.ndarray:
    joint = ix * ny + iy
    if nx * ny <= max(_BINCOUNT_LIMIT, 4 * len(joint)):
        return np.bincount(joint, minlength=nx * ny)
    return np.unique(joint, return_counts=True)[1]


def _check_repeats(repeats: int) -> None:
    if int(repeats) < 1:
        raise ValueError(f"repeats must be ≥ 1, got {repeats}")


def _check_bits(bits: np.ndarray, name: str = "bits") -> np.ndarray:
    b = np.asarray(bits)
    if b.ndim < 1:
        raise ValueError(f"{name} must have a trailing bit axis, got a scalar")
    k = b.shape[-1]
    if k < 1 or k > MAX_BITS:
        raise ValueError(f"{name} must have 1 ≤ k ≤ {MAX_BITS} bits on its last axis, got k={k}")
    if b.size and not np.all((b == 0) | (b == 1)):
        raise ValueError(f"{name} must contain only 0/1 values (discretise messages before measuring them)")
    return b.astype(np.int64)


class _Pairing:
    """Dense codes of one (x, y) pairing, so the marginal entropies are computed once for all shuffle repeats."""

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        self.ix, self.nx = _codes(x)
        self.iy, self.ny = _codes(y)
        self.hx = float(_h_counts(np.bincount(self.ix)))
        self.hy = float(_h_counts(np.bincount(self.iy)))

    def mi(self, iy: np.ndarray | None = None) -> float:
        hxy = float(_h_counts(_joint_counts(self.ix, self.iy if iy is None else iy, self.ny, self.nx)))
        return max(0.0, self.hx + self.hy - hxy)

    def shuffled(self, rng: np.random.Generator, repeats: int) -> np.ndarray:
        return np.array([self.mi(self.iy[rng.permutation(len(self.iy))]) for _ in range(repeats)])


def _bits_and_actions(bits: np.ndarray, actions: np.ndarray, dims: str) -> tuple[np.ndarray, np.ndarray]:
    """``bits [dims…, k]`` and ``actions [dims…]`` checked to agree (``dims`` as written in the error: "M, N")."""
    b, act = _check_bits(bits), np.asarray(actions)
    nd = len(dims.split(","))
    if b.ndim != nd + 1:
        raise ValueError(f"bits must be [{dims}, k], got shape {b.shape}")
    if act.ndim != nd:
        raise ValueError(f"actions must be [{dims}], got shape {act.shape}")
    if b.shape[:nd] != act.shape:
        raise ValueError(f"bits [{dims}, k] and actions [{dims}] disagree: {b.shape} vs {act.shape}")
    return b, act


def _per_bit_codes(b: np.ndarray, iy: np.ndarray, ny: int) -> np.ndarray:
    """MI(bit_j; y) for all j at once from a [k, 2, ny] table built with a single bincount."""
    k = b.shape[1]
    code = ((np.arange(k, dtype=np.int64) * 2 + b) * ny + iy[:, None]).reshape(-1)
    table = np.bincount(code, minlength=k * 2 * ny).reshape(k, 2, ny)
    mi = _h_counts(table.sum(axis=2)) + _h_counts(table.sum(axis=1)) - _h_counts(table.reshape(k, -1))
    return np.maximum(mi, 0.0)


# ---------------------------------------------------------------------------------------------------------------------
# estimators


def symbols(bits: np.ndarray) -> np.ndarray:
    """Pack binary messages [..., k] (0/1 floats or ints, k ≤ 62) into int64 symbols [...] (bit j has weight 2**j)."""
    b = _check_bits(bits)
    return (b << np.arange(b.shape[-1], dtype=np.int64)).sum(axis=-1)


def entropy(x: np.ndarray) -> float:
    """Plug-in entropy in nats of the discrete samples x (1-D, any hashable ints)."""
    counts = np.unique(_as_1d(x, "x"), return_counts=True)[1]
    return max(0.0, float(_h_counts(counts)))


def mutual_information(x: np.ndarray, y: np.ndarray) -> float:
    """Plug-in MI in nats from co-occurrence counts of paired 1-D int samples (H(x)+H(y)-H(x,y), clipped at ≥ 0)."""
    return _Pairing(*_paired(x, y)).mi()


def shuffled_mi(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, repeats: int = 20) -> tuple[float, float]:
    """Mean and std of MI after permuting y relative to x: the plug-in bias at this sample size and vocabulary."""
    _check_repeats(repeats)
    vals = _Pairing(*_paired(x, y)).shuffled(rng, int(repeats))
    return float(vals.mean()), float(vals.std(ddof=1) if len(vals) > 1 else 0.0)


def per_bit_mi(bits: np.ndarray, y: np.ndarray) -> np.ndarray:
    """MI(bit_j ; y) for every bit j of bits [M, k] → [k] (2-symbol vocabularies: little plug-in bias)."""
    b = _check_bits(bits)
    if b.ndim != 2:
        raise ValueError(f"bits must be [M, k], got shape {b.shape}")
    ya = _as_1d(y, "y")
    if b.shape[0] != len(ya):
        raise ValueError(f"bits and y must have the same number of samples, got {b.shape[0]} and {len(ya)}")
    if b.shape[0] == 0:
        raise ValueError("bits is empty")
    iy, ny = _codes(ya)
    return _per_bit_codes(b, iy, ny)


# ---------------------------------------------------------------------------------------------------------------------
# figures


@dataclass(frozen=True)
class MetricFigure:
    """One row of the metrics table: a value with the baselines that say whether it means anything."""

    name: str  # as the table shows it
    key: str  # as JSON stores it
    value: float
    unit: str  # nats, bits, …
    shuffled: float | None = None  # the same figure with messages shuffled across samples: chance level
    shuffled_std: float | None = None  # its spread over the shuffles
    per_bit: float | None = None  # mean over message bits taken one at a time
    per_bit_shuffled: float | None = None
    samples: int | None = None
    note: str = ""  # what was skipped and why


def _pair_stats(
    pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]], rng: np.random.Generator, repeats: int
) -> tuple[list[float], float, float, float, float]:
    """MI per (symbols, bits, actions) pairing plus baselines averaged over pairings.

    The shuffled std is taken over repeats of the pair-averaged baseline, so it is on the same footing as the
    pair-averaged value it is compared with.
    """
    values, shuffled, per_bit, per_bit_sh = [], [], [], []
    for sym, b, act in pairs:
        p = _Pairing(sym, act)
        values.append(p.mi())
        shuffled.append(p.shuffled(rng, repeats))
        per_bit.append(_per_bit_codes(b, p.iy, p.ny).mean())
        n = len(p.iy)
        per_bit_sh.append(np.mean([_per_bit_codes(b, p.iy[rng.permutation(n)], p.ny).mean() for _ in range(repeats)]))
    sh = np.mean(shuffled, axis=0)
    sh_std = float(sh.std(ddof=1)) if repeats > 1 else 0.0
    return values, float(sh.mean()), sh_std, float(np.mean(per_bit)), float(np.mean(per_bit_sh))


def speaker_consistency(
    bits: np.ndarray, actions: np.ndarray, rng: np.random.Generator, repeats: int = 20
) -> MetricFigure:
    """bits [M, N, k] messages each agent sent, actions [M, N] its own action at the same step.

    MI(agent i's message symbol, agent i's action) — positive signalling: does what a speaker says depend on what
    it does? Averaged over agents with more than one distinct action (the others carry no information).
    """
    _check_repeats(repeats)
    b, act = _bits_and_actions(bits, actions, "M, N")
    m, n_agents = act.shape
    if m == 0 or n_agents == 0:
        raise ValueError(f"bits and actions are empty (M={m}, N={n_agents})")
    sym = symbols(b)
    kept = [i for i in range(n_agents) if len(np.unique(act[:, i])) > 1]
    skipped = [i for i in range(n_agents) if i not in kept]
    name, key = "Speaker consistency (positive signalling)", "speaker_consistency"
    if not kept:
        return MetricFigure(name, key, 0.0, "nats", samples=m, note="no agent has more than one action")
    values, sh, sh_std, pb, pb_sh = _pair_stats([(sym[:, i], b[:, i], act[:, i]) for i in kept], rng, int(repeats))
    note = f"agents {len(kept)}/{n_agents}"
    if skipped:
        note += f", skipped single-action agents {skipped}"
    return MetricFigure(name, key, float(np.mean(values)), "nats", sh, sh_std, pb, pb_sh, m, note)


def instantaneous_coordination(
    bits: np.ndarray, actions: np.ndarray, rng: np.random.Generator, repeats: int = 20, delay: int = 0
) -> MetricFigure:
    """MI(speaker i's message at t − delay, listener j's action at t), averaged over ordered pairs i ≠ j.

    Positive listening in the paper's sense: does what one agent hears change what it does? bits [T, B, N, k] and
    actions [T, B, N] keep the time axis so that delay (0 = heard the same step, 1 = DIAL's messages from t−1) can
    pair them; samples = (T − delay)·B. Listeners with a single distinct action are skipped.
    """
    _check_repeats(repeats)
    b, act = _bits_and_actions(bits, actions, "T, B, N")
    t_len, batch, n_agents = act.shape
    if t_len == 0 or batch == 0:
        raise ValueError(f"bits and actions are empty (T={t_len}, B={batch})")
    if n_agents < 2:
        raise ValueError(f"bits and actions need at least 2 agents for speaker→listener pairs, got N={n_agents}")
    if not 0 <= int(delay) < t_len:
        raise ValueError(f"delay must be in [0, T) = [0, {t_len}), got {delay}")
    delay = int(delay)
    samples = (t_len - delay) * batch
    b_said = b[: t_len - delay].reshape(samples, n_agents, -1)  # message heard at t, sent at t − delay
    a_done = act[delay:].reshape(samples, n_agents)
    sym = symbols(b_said)
    listeners = [j for j in range(n_agents) if len(np.unique(a_done[:, j])) > 1]
    pairs = [(i, j) for j in listeners for i in range(n_agents) if i != j]
    name = "Instantaneous coordination (positive listening)" + (f", delay {delay}" if delay else "")
    key = "instantaneous_coordination" + (f"_delay{delay}" if delay else "")
    if not pairs:
        return MetricFigure(name, key, 0.0, "nats", samples=samples, note="no listener has more than one action")
    data = [(sym[:, i], b_said[:, i], a_done[:, j]) for i, j in pairs]
    values, sh, sh_std, pb, pb_sh = _pair_stats(data, rng, int(repeats))
    best = int(np.argmax(values))
    note = f"best pair {pairs[best][0]}→{pairs[best][1]}: {values[best]:.2f}; pairs {len(pairs)}"
    if len(listeners) < n_agents:
        note += f", skipped single-action listeners {[j for j in range(n_agents) if j not in listeners]}"
    return MetricFigure(name, key, float(np.mean(values)), "nats", sh, sh_std, pb, pb_sh, samples, note)


def message_entropy(bits: np.ndarray) -> MetricFigure:
    """Entropy of the message symbols bits [M, N, k], averaged over agents.

    A channel that never varies cannot carry information, so this bounds both MI figures; the plug-in estimate
    saturates at ln M, hence the maximum in the note is ln min(2**k, M).
    """
    b = _check_bits(bits)
    if b.ndim != 3:
        raise ValueError(f"bits must be [M, N, k], got shape {b.shape}")
    m, n_agents, k = b.shape
    if m == 0 or n_agents == 0:
        raise ValueError(f"bits is empty (M={m}, N={n_agents})")
    sym = symbols(b)
    value = float(np.mean([entropy(sym[:, i]) for i in range(n_agents)]))
    p1 = b.mean(axis=0)
    per_bit = float(np.mean(_h_counts(np.stack([p1, 1.0 - p1], axis=-1))))
    h_max = min(k * np.log(2.0), np.log(m))
    return MetricFigure(
        "Message entropy", "message_entropy", value, "nats", per_bit=per_bit, samples=m, note=f"max {h_max:.3f}"
    )


# ---------------------------------------------------------------------------------------------------------------------
# reporting


def _fmt(v: float | None, unit: str) -> str:
    if v is None:
        return ""
    return f"{v:.2f}" if unit in ("return", "L2") else f"{v:.3f}"


def metrics_table(figures: list[MetricFigure], title: str = "") -> str:
    """Table 1 of the paper ('Emergent Communication Metric Used | Value') plus the baselines that qualify it, as
    Markdown."""
    header = ["Emergent Communication Metric Used", "Value", "shuffled baseline", "per bit", "per bit (shuffled)",
              "samples", "note"]  # fmt: skip
    rows = []
    for f in figures:
        shuffled = _fmt(f.shuffled, f.unit)
        if shuffled and f.shuffled_std is not None:
            shuffled += f" ± {_fmt(f.shuffled_std, f.unit)}"
        cells = [
            f.name,
            ("yes" if f.value else "no") if f.unit == "yes/no" else f"{_fmt(f.value, f.unit)} {f.unit}",
            shuffled,
            _fmt(f.per_bit, f.unit),
            _fmt(f.per_bit_shuffled, f.unit),
            "" if f.samples is None else str(f.samples),
            f.note,
        ]
        rows.append([c.replace("|", "\\|") for c in cells])
    table = markdown_table(header, rows, right=[False, *[True] * 5, False])
    return (f"### {title}\n\n" if title else "") + table + "\n"


def _pyplot():
    plt = pyplot()

    return plt


def plot_figures(figures: list[MetricFigure], path: str | Path, title: str = "") -> Path:
    """PNG bar chart: each nats figure beside its shuffled baseline, and the per-bit figures beside theirs."""
    plt = _pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    nats = [f for f in figures if f.unit == "nats"]
    bitwise = [f for f in nats if f.per_bit is not None]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    width = 0.38
    panels = (
        (ax1, nats, lambda f: f.value, lambda f: f.shuffled, lambda f: f.shuffled_std, "whole message (nats)"),
        (ax2, bitwise, lambda f: f.per_bit, lambda f: f.per_bit_shuffled, lambda f: None, "mean per bit (nats)"),
    )
    for ax, figs, val, base, err, label in panels:
        ax.set_title(label)
        if not figs:
            ax.text(0.5, 0.5, "no figures", ha="center", va="center", transform=ax.transAxes)
            ax.set_xticks([])
            continue
        x = np.arange(len(figs))
        ax.bar(x - width / 2, [val(f) for f in figs], width, label="measured", color="tab:blue")
        bx = [i for i, f in enumerate(figs) if base(f) is not None]
        if bx:
            errs = [err(figs[i]) or 0.0 for i in bx]
            ax.bar(
                x[bx] + width / 2,
                [base(figs[i]) for i in bx],
                width,
                yerr=errs if any(errs) else None,
                capsize=3,
                label="shuffled pairs",
                color="tab:gray",
            )
        ax.set_xticks(x)
        ax.set_xticklabels([f.name.split(" (")[0] for f in figs], rotation=15, ha="right", fontsize=8)
        ax.set_ylabel("nats")
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def cooccurrence_plot(
    x: np.ndarray, y: np.ndarray, path: str | Path, xlabel: str, ylabel: str, max_symbols: int = 32
) -> Path:
    """PNG heat-map of the joint distribution p(x, y) of (message symbol, action).

    Only the max_symbols most frequent values on each axis are drawn (so a 2-byte vocabulary stays readable); the
    probabilities are of the whole sample, and the title says how much of it the drawn cells cover.
    """
    if int(max_symbols) < 1:
        raise ValueError(f"max_symbols must be ≥ 1, got {max_symbols}")
    xa, ya = _paired(x, y)
    xu, ix = np.unique(xa, return_inverse=True)
    yu, iy = np.unique(ya, return_inverse=True)
    ix, iy = ix.reshape(-1), iy.reshape(-1)
    top_x = np.sort(np.argsort(-np.bincount(ix), kind="stable")[: int(max_symbols)])
    top_y = np.sort(np.argsort(-np.bincount(iy), kind="stable")[: int(max_symbols)])
    joint = np.bincount(ix * len(yu) + iy, minlength=len(xu) * len(yu)).reshape(len(xu), len(yu))
    p = joint[np.ix_(top_x, top_y)] / len(xa)

    plt = _pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(max(4.0, 0.28 * len(top_x) + 2.0), max(3.0, 0.28 * len(top_y) + 1.6)))
    im = ax.imshow(p.T, origin="lower", aspect="auto", cmap="viridis", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="p(x, y)")
    ax.set_xticks(np.arange(len(top_x)))
    ax.set_xticklabels([str(v) for v in xu[top_x]], rotation=90, fontsize=7)
    ax.set_yticks(np.arange(len(top_y)))
    ax.set_yticklabels([str(v) for v in yu[top_y]], fontsize=7)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(
        f"top {len(top_x)}/{len(xu)} × {len(top_y)}/{len(yu)} values, {p.sum():.0%} of {len(xa)} samples", fontsize=9
    )
    return save_figure(fig, path)
