"""The emergent-communication analysis of a trained policy (the paper's Table 1): what ``convoy analyze`` runs.

It plays the greedy policy, records every agent's message and action at every step, and reports (figures from
``analysis/comm_metrics.py``, which follows Lowe et al. 2019):

* speaker consistency MI(agent's message, its own action) and instantaneous coordination MI(speaker's message at t,
  listener's action after hearing it), each next to its shuffled-pairs baseline and per message bit, with the
  number of samples — a 2-byte vocabulary biases plug-in MI upward, so the raw figure alone proves little;
* causal influence of communication: the same MI where the message was put there by intervention (each listener
  also acts, at every recorded step, on the messages sent in another env), so only the message's effect counts;
* message entropy;
* the message-input norm: the L2 norm of the listener policy's first-layer weights on its message inputs (next to
  the same norm on its observation inputs, per weight, for scale);
* the return with the true messages and with the controls in their place — messages shuffled across envs, each
  sender's modal message, all-zero messages, white noise (and, for the ``-mm`` variants, the memory module's
  predictions and no channel) — each paired with the true messages;
* whether a protocol formed: the listeners act on the messages and the true ones beat the in-distribution controls.

Samples come from ``B`` envs stepped for ``T`` steps with auto-reset (the policy's own state distribution, several
episodes per env), so the time axis is kept for the speaker → listener pairing.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from convoy.actors.stepping import EnvStepper
from convoy.algos.algorithm import Agent
from convoy.algos.entity import EntityEncoder
from convoy.algos.listening import HearsMessages, Listening, Source
from convoy.algos.memory import MemoryModule
from convoy.analysis.comm_metrics import (
    MetricFigure,
    cooccurrence_plot,
    instantaneous_coordination,
    message_entropy,
    metrics_table,
    plot_figures,
    speaker_consistency,
    symbols,
)
from convoy.analysis.evaluation import evaluate_policy, listening
from convoy.analysis.probe import adversary_sector, code_words, own_place, probe_figures
from convoy.envs.batched import BatchedEnv
from convoy.envs.treadmill.engine import TreadmillEngine
from convoy.stats import ci95_half
from convoy.validation import ConfigError


@dataclass
class Recording:
    """Messages sent ``[T, B, N, bits]`` and actions taken ``[T, B, N]`` by the greedy policy; and, at the same
    steps, the messages the intervention put in each env's place (those sent in another env, ``[T, B, N, bits]``)
    with the greedy actions every agent would have taken hearing them instead (``[T, B, N]``)."""

    messages: np.ndarray
    actions: np.ndarray
    intervened_messages: np.ndarray
    intervened_actions: np.ndarray
    # on the treadmill, for the decoding probe (``analysis/probe.py``), ``[T, B, N]`` and ``[T, B, N, 16]``: where
    # only teammates observe the adversary and its direction, and the 16-bit code word each agent would send
    probe_valid: np.ndarray | None = None
    probe_label: np.ndarray | None = None
    code_words: np.ndarray | None = None
    place: np.ndarray | None = None  # [T, B, N, 2] each agent's place on the window


class Intervention(Listening):
    """Every receiver hears the messages sent in another env at the same step (``shuffled``), and the derangement
    it used is kept (``perm``: env b heard env ``perm[b]``), so each intervened action pairs with the message that
    caused it."""

    def __init__(self, seed: int) -> None:
        super().__init__("shuffled", seed=seed)
        self.perm: Tensor | None = None

    def _derangement(self, n: int) -> Tensor:
        self.perm = super()._derangement(n)
        return self.perm


@dataclass
class Analysis:
    """Every figure of the table, plus where the files went."""

    algo: str
    env: str
    figures: list[MetricFigure]
    files: dict[str, str] = field(default_factory=dict)

    @property
    def title(self) -> str:
        return f"Emergent communication of {self.algo} on {self.env}"

    def table(self) -> str:
        return metrics_table(self.figures, title=self.title)

    def as_dict(self) -> dict:
        return {"algo": self.algo, "env": self.env, "figures": [asdict(f) for f in self.figures], "files": self.files}


def check_analysable(algo: Agent) -> HearsMessages:
    """``algo`` as a listener of discrete per-agent messages, or a ConfigError that says which algorithms are."""
    if not isinstance(algo, HearsMessages):
        raise ConfigError(
            "checkpoint",
            f"{algo.name} sends no discrete per-agent messages to analyse; analyse ma-mesn, ma-bon or their -mm "
            "variants",
        )
    return algo


@torch.no_grad()
def record(
    algo: Agent, env: BatchedEnv, steps: int, seed: int, progress: Callable[[int, int], None] | None = None
) -> Recording:
    """``steps`` greedy steps of every env (auto-reset), recording messages and actions; at each step, before it
    is taken, the actions every agent would take hearing another env's messages (the causal intervention: same
    observation and memory, only what is heard replaced). ``progress(done, steps)`` is called after each step."""
    check_analysable(algo)
    stepper = EnvStepper(env, algo, seed, record=False)
    intervention = Intervention(seed)
    msgs, acts, i_msgs, i_acts = [], [], [], []
    engine = env if isinstance(env, TreadmillEngine) else None
    valid, label, words, place = [], [], [], []
    for _ in range(steps):
        if engine is not None:  # what only teammates know now, before the agents speak about it
            v, lab = adversary_sector(engine)
            valid.append(v)
            label.append(lab)
            words.append(code_words(stepper.obs, engine))
            place.append(own_place(stepper.obs))
        with listening(algo, intervention):
            i_acts.append(algo.act(stepper.obs, 0.0, stepper.state).actions)
        stepper.step(0.0)
        assert stepper.last is not None and stepper.last.messages is not None and intervention.perm is not None
        msgs.append(stepper.last.messages)
        acts.append(stepper.last.actions)
        i_msgs.append(stepper.last.messages[intervention.perm.cpu().numpy()])
        if progress is not None:
            progress(len(msgs), steps)
    as_bits = lambda m: np.stack(m).round().astype(np.int8)  # noqa: E731
    rec = Recording(as_bits(msgs), np.stack(acts), as_bits(i_msgs), np.stack(i_acts))
    if engine is not None:
        rec = replace(
            rec,
            probe_valid=np.stack(valid),
            probe_label=np.stack(label),
            code_words=np.stack(words),
            place=np.stack(place),
        )
    return rec


def message_input_norm(algo: Agent) -> MetricFigure:
    """L2 norm of the policy network's first-layer weights on its message inputs (mean over listener groups)."""
    listener = check_analysable(algo)
    policy = listener.evaluated["policy"]
    width = listener.senders * listener.bits
    if isinstance(policy, torch.nn.Sequential) and isinstance(policy[0], EntityEncoder):
        # encoder=entity: each message enters through ψ's first layer, each car through φ's
        msg_w = policy.get_parameter("0.heard.layers.0.weight").detach()[0]  # the run's (a run of one)
        obs_w = policy.get_parameter("0.car.layers.0.weight").detach()[0]
    else:
        first = policy.get_parameter("layers.0.weight").detach()[0]  # the run's [G, inputs, out]: messages last
        msg_w, obs_w = first[:, -width:], first[:, :-width]
    msg_norm = float(msg_w.flatten(1).norm(dim=1).mean())
    obs_norm = float(obs_w.flatten(1).norm(dim=1).mean())
    rms_ratio = (msg_norm / math.sqrt(msg_w[0].numel())) / max(obs_norm / math.sqrt(obs_w[0].numel()), 1e-12)
    return MetricFigure(
        name="Message input norm (MIN)",
        key="message_input_norm",
        value=msg_norm,
        unit="L2",
        note=f"{width} message inputs; observation-input norm {obs_norm:.2f}; per-weight RMS message/obs "
        f"{rms_ratio:.2f}",
    )


def return_figures(
    algo: Agent, env: BatchedEnv, episodes: int, seed: int, say: Callable[[str], None] | None = None
) -> tuple[list[MetricFigure], dict[str, np.ndarray]]:
    """Greedy return with the true messages and with each control in their place, on the same episodes: messages
    shuffled across envs and each sender's modal message (in distribution: real messages, no content), all-zero
    messages (what a cut channel delivers), white noise (out of distribution) and, for memory modules, their
    predictions. Each control's note gives its paired difference from the true messages with a 95 % CI (the
    differences come back by source): the messages matter where true beats the in-distribution controls."""
    sources: list[Source] = ["sent", "shuffled", "modal", "fixed", "noise"]
    if isinstance(algo, MemoryModule):
        sources.append("predicted")
    names = {
        "sent": "Cumulative reward (true messages)",
        "shuffled": "Cumulative reward with messages shuffled across envs",
        "modal": "Cumulative reward with each sender's modal message",
        "fixed": "Cumulative reward with every message all zeros",
        "noise": "Cumulative reward with white noise",
        "predicted": "Cumulative reward with predicted messages (no channel)",
    }
    out, true = [], None
    diffs: dict[str, np.ndarray] = {}
    for i, src in enumerate(sources):
        if say is not None:
            say(f"return figures: {episodes} episodes with {src} messages ({i + 1}/{len(sources)})")
        res = evaluate_policy(algo, env, episodes, seed=seed, messages=src)
        note = f"± {res.ci95:.2f} (95 % CI)"
        if true is None:
            true = res.returns
        else:
            diff = diffs[src] = res.returns - true  # the same episodes: paired
            note += f"; paired vs true {diff.mean():+.2f} ± {ci95_half(diff, single=0.0):.2f}"
        out.append(MetricFigure(name=names[src], key=f"return_{src}", value=res.mean, unit="return",
                                samples=len(res.returns), note=note))  # fmt: skip
    return out, diffs


def protocol_formed(cic: MetricFigure, diffs: dict[str, np.ndarray]) -> MetricFigure:
    """Whether this policy's messages form a protocol: its listeners act on them (causal influence more than
    three shuffle deviations above its baseline) *and* they pay (the true messages beat both in-distribution
    controls, shuffled and modal, paired 95 % CIs above 0). 1 or 0, so its mean over seeds is the fraction of
    seeds where a protocol formed."""
    base = (cic.shuffled or 0.0) + 3 * (cic.shuffled_std or 0.0)
    acts = cic.value > base
    pays = {
        src: float(-d.mean() - ci95_half(-d, single=np.inf)) for src, d in diffs.items() if src in ("shuffled", "modal")
    }
    formed = acts and len(pays) == 2 and min(pays.values()) > 0
    gains = ", ".join(f"true − {src} ≥ {low:+.2f}" for src, low in pays.items())
    note = f"influence {cic.value:.3f} vs {base:.3f} ({'acts' if acts else 'does not act'} on messages); {gains}"
    return MetricFigure("Protocol formed (acts on messages and they pay)", "protocol", float(formed), "yes/no",
                        note=note)  # fmt: skip


def analyze(
    algo: Agent,
    env: BatchedEnv,
    env_name: str,
    steps: int,
    episodes: int,
    seed: int,
    out_dir: str | Path | None = None,
    repeats: int = 20,
    progress: Callable[[int, int], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> Analysis:
    """Table 1 for ``algo``: communication figures from ``steps × B`` samples, returns from ``episodes`` episodes.
    ``progress(done, steps)`` follows the recording, ``say`` is told each later stage."""
    rec = record(algo, env, steps, seed, progress)
    if say is not None:
        say(f"mutual-information figures ({repeats} shuffles per baseline)")
    rng = np.random.default_rng(seed)
    t, b, n, k = rec.messages.shape
    flat_msgs, flat_acts = rec.messages.reshape(t * b, n, k), rec.actions.reshape(t * b, n)
    sc = speaker_consistency(flat_msgs, flat_acts, rng, repeats)
    ic = instantaneous_coordination(rec.messages, rec.actions, rng, repeats)
    cic = causal_influence(rec, rng, repeats)
    returns, diffs = return_figures(algo, env, episodes, seed, say)
    figures = [sc, ic, cic, message_entropy(flat_msgs), message_input_norm(algo), *returns, protocol_formed(cic, diffs)]
    words, place, valid, label = rec.code_words, rec.place, rec.probe_valid, rec.probe_label
    if (
        words is not None
        and place is not None
        and valid is not None
        and label is not None
        and n > 1
        and rec.messages.shape[2] == words.shape[2]  # one message per agent (not MA-BoN's broadcast)
    ):
        figures += probe_figures(rec.messages, words, place, valid, label)
    result = Analysis(algo.name, env_name, figures)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        result.files["table"] = str(out / "table.md")
        result.files["json"] = str(out / "analysis.json")
        result.files["metrics_png"] = str(plot_figures(figures, out / "metrics.png", title=result.title))
        speaker, listener = _best_pair(rec, env.spec.n_actions)
        result.files["cooccurrence_png"] = str(
            cooccurrence_plot(
                symbols(rec.messages[:, :, speaker]).ravel(),
                rec.actions[:, :, listener].ravel(),
                out / "cooccurrence.png",
                xlabel=f"message of {env.spec.agent_ids[speaker]} (symbol)",
                ylabel=f"action of {env.spec.agent_ids[listener]}",
            )
        )
        Path(result.files["table"]).write_text(result.table() + "\n")
        Path(result.files["json"]).write_text(json.dumps(result.as_dict(), indent=2) + "\n")
    return result


def causal_influence(rec: Recording, rng: np.random.Generator, repeats: int = 20) -> MetricFigure:
    """Causal influence of communication (Lowe et al. 2019): MI(speaker i's message, listener j's action) where
    the message was put there by intervention — sent in another env, so unrelated to the listener's own state —
    and the action is the one the listener takes on hearing it. Any dependence is then the message's effect; the
    shuffled-pairs baseline is the estimator's bias. Pooled over states, it is a lower bound on Lowe et al.'s
    per-state CIC. The note adds how often the intervention changed a listener's action at all (over agents with
    more than one action)."""
    fig = instantaneous_coordination(rec.intervened_messages, rec.intervened_actions, rng, repeats)
    acts, moved = rec.actions.reshape(-1, rec.actions.shape[-1]), rec.intervened_actions != rec.actions
    listeners = [j for j in range(acts.shape[1]) if len(np.unique(acts[:, j])) > 1]  # as the MI figures count them
    changed = float(moved[..., listeners].mean()) if listeners else 0.0
    return replace(
        fig,
        name="Causal influence of communication (messages from another env)",
        key="causal_influence",
        note=f"{fig.note}; the intervention changed {changed:.1%} of listener actions",
    )


def _best_pair(rec: Recording, n_actions: tuple[int, ...]) -> tuple[int, int]:
    """The (speaker, listener) pair to draw: the first listener with a choice, heard from its first peer."""
    n = rec.actions.shape[-1]
    listeners = [j for j in range(n) if n_actions[j] > 1] or [0]
    j = listeners[0]
    i = next((s for s in range(n) if s != j), j)
    return i, j
