"""A decoding probe: is what teammates observe in the messages a listener hears?

Causal influence says whether listeners *act* on messages; a return gap says whether messages *pay*. Neither says
whether the information is *there*. The probe asks it directly, on the treadmill: at the steps where the adversary
is observed by some teammate and not by the listener itself — the only steps where a message can tell the listener
something new about it — how well does a small classifier, fitted on one half of the recorded rollouts and scored on
the other, recover the adversary's compass direction from the listener (one of 8) from what the listener heard and
where it is itself (a word may name a window cell, which needs the listener's own place to become a direction)? It
is scored beside the same probe on the listener's place alone (what it could guess without hearing anything: the
chaser comes from behind more often) and on a hand-designed 16-bit code (``envs.treadmill.drivers.encode16``, the
team16 driver's word: the cell of the car a teammate sees closing in fastest), which carries the chaser's cell by
design: a learned channel that carries the information scores near that. The messages are those sent, which on an
open channel are those heard; a channel-cut twin's speakers send too, though no listener hears them, so its figure
is that of a message network no listener shaped (measured at mid: 0.30 against 0.27 from the place alone).
"""

from __future__ import annotations

import numpy as np
import torch

from convoy.analysis.comm_metrics import MetricFigure
from convoy.envs.treadmill.config import LONGITUDINAL
from convoy.envs.treadmill.drivers import encode16, peer_index
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.envs.treadmill.scripted import heading_towards

SECTORS = 8


def adversary_sector(engine: TreadmillEngine) -> tuple[np.ndarray, np.ndarray]:
    """``(valid, label)`` ``[B, N]``: whether some teammate observes an adversary that the agent does not (the
    closest such adversary), and its compass direction from the agent (0 … 7)."""
    cfg = engine.cfg
    n = cfg.n_agents
    near, near_dist, _ = engine.nearest()
    seen = (near[..., None] == np.arange(cfg.n_cars)) & np.isfinite(near_dist)[..., None]  # [B, N, k, C]
    sees = seen.any(axis=2)  # [B, N, C]: agent i observes car c
    by_others = (sees.sum(axis=1, keepdims=True) - sees) > 0  # some other agent observes c
    new = by_others & ~sees & (np.arange(cfg.n_cars) >= n)  # an adversary only teammates observe
    rel_x, rel_y = engine.offsets()
    dist = np.where(new, np.hypot(rel_x, rel_y), np.inf)
    c = np.argmin(dist, axis=2)[..., None]
    valid = np.isfinite(np.take_along_axis(dist, c, axis=2)[..., 0])
    dx = np.take_along_axis(rel_x, c, axis=2)[..., 0]
    dy = np.take_along_axis(rel_y, c, axis=2)[..., 0]
    return valid, heading_towards(dx, dy)


def code_words(obs: np.ndarray, engine: TreadmillEngine) -> np.ndarray:
    """Every agent's 16-bit code word (``encode16``) as bits ``[B, N, 16]``: the reference channel of the probe."""
    words = encode16(obs, engine.cfg).astype(np.int64)
    return ((words[..., None] >> np.arange(16)) & 1).astype(np.int8)


def heard(bits: np.ndarray) -> np.ndarray:
    """What each agent hears from its peers ``[..., N, (N−1)·bits]`` from everyone's bits ``[..., N, bits]``."""
    n = bits.shape[-2]
    return bits[..., peer_index(n), :].reshape(*bits.shape[:-2], n, -1)


def probe_accuracy(
    features: np.ndarray, labels: np.ndarray, valid: np.ndarray, seed: int = 0
) -> tuple[float, float, int]:
    """(test accuracy, majority-class accuracy, test samples) of a one-hidden-layer classifier from ``features``
    ``[T, B, N, F]`` to ``labels`` ``[T, B, N]`` at the ``valid`` steps, fitted on the first half of the steps and
    scored on the second (other rollouts of the same policy)."""
    half = features.shape[0] // 2
    x_tr, y_tr = features[:half][valid[:half]], labels[:half][valid[:half]]
    x_te, y_te = features[half:][valid[half:]], labels[half:][valid[half:]]
    if not len(y_tr) or not len(y_te):
        return float("nan"), float("nan"), 0
    majority = float((y_te == np.bincount(y_tr, minlength=SECTORS).argmax()).mean())
    gen = torch.Generator().manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(x_tr.shape[1], 64), torch.nn.ReLU(), torch.nn.Linear(64, SECTORS))
    for p in net.parameters():  # seeded init, so the figure repeats
        torch.nn.init.uniform_(p, -0.1, 0.1, generator=gen)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    xt, yt = torch.as_tensor(x_tr, dtype=torch.float32), torch.as_tensor(y_tr, dtype=torch.long)
    with torch.enable_grad():
        for _ in range(300):  # full batch: a few thousand samples
            loss = torch.nn.functional.cross_entropy(net(xt), yt)
            opt.zero_grad()
            loss.backward()
            opt.step()
    with torch.no_grad():
        pred = net(torch.as_tensor(x_te, dtype=torch.float32)).argmax(dim=-1).numpy()
    return float((pred == y_te).mean()), majority, len(y_te)


def own_place(obs: np.ndarray) -> np.ndarray:
    """Each agent's place on the window ``[B, N, 2]`` (lateral, longitudinal) from its observation."""
    return np.stack([obs[..., 0], obs[..., LONGITUDINAL]], axis=-1)


def probe_figures(
    messages: np.ndarray, words: np.ndarray, place: np.ndarray, valid: np.ndarray, labels: np.ndarray
) -> list[MetricFigure]:
    """The probe on the listener's place alone, with the heard messages, and with the heard code words
    (``[T, B, N, bits]`` each; ``place`` ``[T, B, N, 2]``)."""
    out = []
    for key, name, features in (
        ("probe_place", "Decoding probe: a chaser only teammates see, from the listener's place alone", place),
        ("probe_messages", "Decoding probe: the same, from the messages heard (and the place)",
         np.concatenate([heard(messages), place], axis=-1)),
        ("probe_code_word", "Decoding probe: the same, from a 16-bit code's words (reference channel)",
         np.concatenate([heard(words), place], axis=-1)),
    ):  # fmt: skip
        acc, majority, samples = probe_accuracy(features.astype(np.float32), labels, valid)
        out.append(
            MetricFigure(
                name=name,
                key=key,
                value=acc,
                unit="accuracy",
                shuffled=majority,
                samples=samples,
                note=f"its compass direction (1 of {SECTORS}); majority class {majority:.3f}, on held-out steps",
            )
        )
    return out
