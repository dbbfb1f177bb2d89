"""The message memory module (section 4.1): an LSTM per agent that predicts, from the agent's own observation
history, the messages the others would send — so the trained cooperative policy can run with no channel at all.

``MemoryModule`` is a mixin over a message-passing algorithm (MA-MeSN, MA-BoN: anything with ``speak``/``listen``/
``hear``, see ``algos/listening.py``). It adds:

* **a history window** as the acting state: each env's last ``memory_window`` observations of every agent
  ``[B, L, N, D + 1]`` (the extra column marks real steps, so the zero padding before an episode's first step is
  distinguishable from an all-zero observation); it is stored with every transition (``history``, float16 to halve
  replay and wire bytes — observations are normalised to about [−1, 1]), so the module trains on exactly the
  inputs it sees at execution;
* **a supervised loss trained in parallel** with centralised training, on the same batch and by the same optimizer:
  binary cross-entropy between the module's bit logits and the messages each agent heard at that step — the
  *execution* messages (argmax, no Gumbel noise) of the current message networks, detached, so the loss reaches
  the memory module only and the TD losses never see it;
* **execution from predictions**: when the evaluation's ``Listening`` asks for them (``predicted``: no channel; a
  lossy channel: predictions replace dropped messages), the policy network reads the prediction ``logits > 0``.

Choices made where the paper is silent: a fixed window (default 8 steps) rather than a carried LSTM state, so a
replayed transition is self-contained (no burn-in, no stored hidden states that go stale as the weights change)
and training and execution read identical inputs; one LSTM layer of ``memory_hidden`` units, its input projection
(torch's fused LSTM when weights are shared); shared or per-agent weights following ``share_params`` (agent id
appended when shared), all agents in one batched call.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.nets import GroupLinear, id_width, with_agent_id

if TYPE_CHECKING:
    from convoy.algos.algorithm import Batch, Loss
    from convoy.algos.listening import HearsMessages
    from convoy.config import BoNMMConfig, MeSNMMConfig

    class _Speaker(HearsMessages):
        """What the mixin sits on, as the type checker reads it (at run time it is a plain class): a message-passing
        algorithm, MA-MeSN or MA-BoN, with its networks, loss, ``speak``, ``listen`` and ``forward``."""

        def build(self) -> dict[str, nn.Module]: ...
        def loss(self, batch: Batch) -> Loss: ...
        def speak(self, nets: nn.ModuleDict, obs: Tensor, train: bool) -> tuple[Tensor, Tensor, Tensor]: ...
        def listen(self, nets: nn.ModuleDict, x: Tensor, heard: Tensor) -> Tensor: ...
        def forward(
            self, nets: nn.ModuleDict, obs: Tensor, train: bool, received: Tensor | None = None
        ) -> tuple[Tensor, Tensor]: ...
else:
    _Speaker = object

HISTORY = "history"


class GroupLSTM(nn.Module):
    """One LSTM per agent group over a window ``[M, L, N, in]`` → logits ``[M, N, out]`` from the last step.

    Shared weights (one group) fold the agents into the batch and run torch's fused ``nn.LSTM`` (one call for the
    whole window: 4.5× faster updates than a Python loop over steps); per-agent weights step a grouped cell, all
    agents in one batched matmul per step.
    """

    lstm: nn.LSTM  # shared weights
    inp: GroupLinear  # per-agent weights: the input and recurrent maps of the grouped cell
    rec: GroupLinear

    def __init__(self, groups: int, in_features: int, hidden: int, out_features: int) -> None:
        super().__init__()
        self.hidden, self.groups = hidden, groups
        if groups == 1:
            self.lstm = nn.LSTM(in_features, hidden, batch_first=True)
            gate_bias = self.lstm.get_parameter("bias_ih_l0")
            self.lstm.get_parameter("bias_hh_l0").data.zero_()
        else:
            self.inp = GroupLinear(groups, in_features, 4 * hidden)
            self.rec = GroupLinear(groups, hidden, 4 * hidden)
            gate_bias = self.inp.bias
            self.rec.bias.data.zero_()
        with torch.no_grad():  # forget gate open at the start (Jozefowicz et al. 2015): memories survive early on
            gate_bias[..., hidden : 2 * hidden].fill_(1.0)
        self.head = GroupLinear(groups, hidden, out_features)

    def forward(self, seq: Tensor) -> Tensor:
        runs = self.head.runs  # stacked runs (``stack_runs``), 0 for one run's module
        if runs == 1 and self.groups == 1:  # a stack of one run: torch's fused LSTM on its weights, its numbers
            weights = {k: v[0] for k, v in self.lstm.named_parameters()}
            last: Tensor = self.head(self._fused(seq[0], weights).unsqueeze(0))  # torch leaves a module call untyped
            return last
        if runs:
            return self._forward_runs(seq)
        if self.groups == 1:
            out: Tensor = self.head(self._fused(seq))
            return out
        m, steps, n, _ = seq.shape
        gates_in = self.inp(seq)  # every step's input projection in one call
        h = seq.new_zeros(m, n, self.hidden)
        c = torch.zeros_like(h)
        for t in range(steps):
            i, f, g, o = (gates_in[:, t] + self.rec(h)).chunk(4, dim=-1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
        out = self.head(h)
        return out

    def _fused(self, seq: Tensor, weights: dict[str, Tensor] | None = None) -> Tensor:
        """The shared weights' last hidden state ``[M, N, hidden]`` of one run's windows ``[M, L, N, in]``: torch's
        fused ``nn.LSTM`` (with ``weights`` in place of its own, a stacked run's)."""
        m, steps, n, width = seq.shape
        flat = seq.permute(0, 2, 1, 3).reshape(m * n, steps, width)  # every agent's window is a sequence
        _, (h, _) = self.lstm(flat) if weights is None else torch.func.functional_call(self.lstm, weights, (flat,))
        last: Tensor = h[-1]
        return last.reshape(m, n, self.hidden)

    def _forward_runs(self, seq: Tensor) -> Tensor:
        """A population's windows ``[R, M, L, N, in]`` → ``[R, M, N, out]``: the grouped cell stepped by hand; with
        shared weights the stacked ``nn.LSTM`` parameters (gates i, f, g, o, as torch orders them) in batched
        matmuls over runs."""
        r, m, steps, n, width = seq.shape
        if self.groups > 1:
            gates_in = self.inp(seq)
            h = seq.new_zeros(r, m, n, self.hidden)
            rec: Callable[[Tensor], Tensor] = self.rec
        else:
            lstm = self.lstm
            flat = seq.reshape(r, -1, width)  # [R, M·L·N, in]
            gates_in = torch.baddbmm(
                lstm.get_parameter("bias_ih_l0").unsqueeze(1), flat, lstm.get_parameter("weight_ih_l0").transpose(1, 2)
            )
            gates_in = gates_in.reshape(r, m, steps, n, 4 * self.hidden)
            h = seq.new_zeros(r, m, n, self.hidden)
            w_hh, b_hh = (
                lstm.get_parameter("weight_hh_l0").transpose(1, 2),
                lstm.get_parameter("bias_hh_l0").unsqueeze(1),
            )

            def rec(h: Tensor) -> Tensor:  # the shared weights' recurrence, stepped by hand
                return torch.baddbmm(b_hh, h.reshape(r, -1, self.hidden), w_hh).reshape(r, m, n, 4 * self.hidden)

        c = torch.zeros_like(h)
        for t in range(steps):
            i, f, g, o = (gates_in[:, :, t] + rec(h)).chunk(4, dim=-1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
        out: Tensor = self.head(h)
        return out


class MemoryModule(_Speaker):
    """Mixin: put it before a ``HearsMessages`` algorithm, e.g. ``class MAMeSNMM(MemoryModule, MAMeSN)``."""

    cfg: MeSNMMConfig | BoNMMConfig  # the rest (networks, device, sizes, ``listening``) the algorithm provides

    def build(self) -> dict[str, nn.Module]:
        nets = super().build()
        self.window = int(self.cfg.memory_window)
        groups = 1 if self.shared else self.n_agents
        width = self.obs_dim + 1 + id_width(self.n_agents, self.shared)
        nets["memory"] = GroupLSTM(groups, width, int(self.cfg.memory_hidden), self.senders * self.bits)
        return nets

    # --- acting: the window is the recurrent state -------------------------------------------------------------
    def initial_state(self, num_envs: int) -> Tensor:
        return torch.zeros(self.runs, num_envs, self.window, self.n_agents, self.obs_dim + 1, device=self.device)

    def reset_runs(self, state: Tensor, done: np.ndarray) -> Tensor:
        state = super().reset_runs(state, done)  # the channel's in-flight messages
        if not done.any():
            return state
        state = state.clone()
        state[torch.as_tensor(done, device=state.device)] = 0.0
        return state

    def push(self, state: Tensor | None, obs: Tensor) -> Tensor:
        """The window after this step: the oldest observation out, ``obs`` (marked real) in."""
        if state is None:
            state = self.initial_state(obs.shape[-3])
        step = torch.cat([obs, obs.new_ones(*obs.shape[:-1], 1)], dim=-1).unsqueeze(-3)
        return torch.cat([state[..., 1:, :, :], step], dim=-3)

    def predict(self, nets: nn.ModuleDict, window: Tensor) -> Tensor:
        """Bit logits ``[M, N, senders·bits]`` of the messages each agent will hear, from its own window."""
        logits: Tensor = nets["memory"](with_agent_id(window.float(), self.shared))
        return logits

    def greedy_q(self, obs: Tensor, state: Any) -> tuple[Tensor, Tensor, Tensor]:
        window = self.push(state, obs)
        x, sent, heard = self.speak(self.online, obs, False)
        predicted = None
        if self.listening is not None and self.listening.needs_prediction:
            predicted = (self.predict(self.online, window) > 0).to(heard.dtype)
        q = self.listen(self.online, x, self.hear(heard.contiguous(), predicted))
        return q, sent.contiguous(), window

    def extras(self, obs: np.ndarray, state: Any = None) -> dict[str, np.ndarray]:
        extra = super().extras(obs, state)
        if state is not None:
            extra[HISTORY] = state.to(torch.float16).cpu().numpy()
        return extra

    # --- learning: supervised, in parallel with the TD losses ---------------------------------------------------
    def loss(self, batch: Batch) -> Loss:
        """The algorithm's own loss, plus the memory module's on the same batch: predict the messages each agent
        hears from its own observation window (no gradient of it reaches the message or policy networks)."""
        return super().loss(batch).plus(*self.memory_loss(batch))

    def memory_loss(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        """``memory_coef`` × the BCE of the predicted bits against the messages each agent truly hears, and the
        prediction's accuracy per bit and per whole message."""
        if HISTORY not in batch:
            raise KeyError(f"{type(self).__name__} needs '{HISTORY}' in its transitions: collect them with its act()")
        logits = self.predict(self.online, batch[HISTORY])
        with torch.no_grad():
            _, _, heard = self.speak(self.online, batch["obs"], False)
            target = heard.reshape(logits.shape)
        per_run = tuple(range(1, logits.dim()))  # figures per run
        bce = F.binary_cross_entropy_with_logits(logits, target, reduction="none").mean(dim=per_run)
        with torch.no_grad():
            right = (logits > 0) == (target > 0.5)
            msg_right = right.reshape(*right.shape[:-1], self.senders, self.bits).all(dim=-1)
        stats = {
            "memory_loss": bce.detach(),
            "memory_bit_acc": right.float().mean(dim=per_run),
            "memory_msg_acc": msg_right.float().mean(dim=tuple(range(1, msg_right.dim()))),
        }
        return self.cfg.memory_coef * bce, stats
