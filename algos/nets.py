"""Network building blocks that evaluate every agent in one pass.

All Convoy algorithms keep the agents' weights stacked: ``GroupLinear`` holds ``[G, in, out]`` with G = 1 when
parameters are shared (the agents then form one big ``[B·N, in] @ [in, out]`` matmul) and G = N otherwise (one
batched ``bmm`` over agents). Either way a forward pass is one call for all agents, never a Python loop, which
keeps the learner's matmuls big and lets the inference-scaling benchmark measure the algorithms, not the loop.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.config import resolved

if TYPE_CHECKING:
    from convoy.config import GumbelConfig


def pick_device(name: str = "auto") -> torch.device:
    """``auto`` means CUDA when present, else CPU; an explicit name is taken as given."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class GroupLinear(nn.Module):
    """A linear layer per agent group: input ``[..., N, in]`` → ``[..., N, out]``.

    A layer as ``build`` makes it is one run's. Stacked (:func:`stack_runs`, what an agent trains: R ≥ 1 runs)
    every weight carries a leading run axis, ``[R, G, in, out]``, inputs are ``[R, ..., N, in]`` and each run's rows
    meet only its own weights: one ``baddbmm`` over runs (and agent groups) instead of a Python loop. A stack of one
    run computes with the one-run kernels, so a single run's numbers are the unstacked layer's bit for bit.
    """

    def __init__(self, groups: int, in_features: int, out_features: int) -> None:
        super().__init__()
        self.groups, self.in_features, self.out_features = groups, in_features, out_features
        self.runs = 0  # stacked runs (``stack_runs``); 0: one run's layer, no run axis
        bound = 1.0 / math.sqrt(max(in_features, 1))
        self.weight = nn.Parameter(torch.empty(groups, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(groups, out_features).uniform_(-bound, bound))

    def forward(self, x: Tensor) -> Tensor:
        if self.runs > 1:
            return self._forward_runs(x)
        if self.runs == 1:  # a stack of one run: the one-run kernels on its weights
            if x.shape[0] != 1:
                raise ValueError(f"GroupLinear of one run expected a run axis of 1 on dim 0, got {tuple(x.shape)}")
            return self._forward_one(x[0], self.weight[0], self.bias[0]).unsqueeze(0)
        return self._forward_one(x, self.weight, self.bias)

    def _forward_one(self, x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        """One run's ``[..., N, in]`` → ``[..., N, out]`` with its weights ``[G, in, out]``."""
        if self.groups == 1:  # one 2-D matmul over every row of every agent (3-D matmuls backprop slowly)
            flat = x.reshape(-1, self.in_features)
            return torch.addmm(bias[0], flat, weight[0]).reshape(*x.shape[:-1], self.out_features)
        n = self._agents(x)
        lead = x.shape[:-2]
        flat = x.reshape(-1, n, self.in_features).transpose(0, 1)  # [N, M, in]
        out = torch.baddbmm(bias.unsqueeze(1), flat, weight)  # [N, M, out]
        return out.transpose(0, 1).reshape(*lead, n, self.out_features)

    def _forward_runs(self, x: Tensor) -> Tensor:
        """``[R, ..., N, in]`` → ``[R, ..., N, out]``: R·G independent matmuls in one ``baddbmm``."""
        r, out_f = x.shape[0], self.out_features
        if self.groups == 1:
            flat = x.reshape(r, -1, self.in_features)
            out = torch.baddbmm(self.bias[:, :1], flat, self.weight[:, 0])  # [R, M·N, out]
            return out.reshape(*x.shape[:-1], out_f)
        n = self._agents(x)
        flat = x.reshape(r, -1, n, self.in_features).transpose(1, 2).reshape(r * n, -1, self.in_features)
        w = self.weight.reshape(r * n, self.in_features, out_f)
        out = torch.baddbmm(self.bias.reshape(r * n, 1, out_f), flat, w)  # [R·N, M, out]
        return out.reshape(r, n, -1, out_f).transpose(1, 2).reshape(*x.shape[:-1], out_f)

    def _agents(self, x: Tensor) -> int:
        n = x.shape[-2]
        if n != self.groups:
            raise ValueError(f"GroupLinear expected {self.groups} agents on dim -2, got {n}")
        return n


M = TypeVar("M", bound=nn.Module)


def stack_runs(modules: Sequence[M]) -> M:
    """One module holding R = len(modules) runs of the same architecture: every ``GroupLinear``'s weights stacked on
    a leading run axis, so run k computes exactly what ``modules[k]`` computes, all runs in one batched call.

    Only ``GroupLinear`` layers, and the ``nn.LSTM`` inside a memory module's ``GroupLSTM`` (which then steps its
    cell by hand), can carry the run axis; any other layer with weights is refused.
    """
    stacked = copy.deepcopy(modules[0])
    named = [dict(m.named_modules()) for m in modules]
    for name, layer in stacked.named_modules():
        own = list(layer.parameters(recurse=False))
        if not own:
            continue
        if not isinstance(layer, GroupLinear | nn.LSTM):
            raise NotImplementedError(
                f"population training: layer {name or 'root'} ({type(layer).__name__}) has no run axis; "
                "train this algorithm one seed per process"
            )
        layer.runs = len(modules)
        for pname, _ in list(layer.named_parameters(recurse=False)):
            value = torch.stack([getattr(n[name], pname).detach() for n in named])
            setattr(layer, pname, nn.Parameter(value))
    return stacked


def run_state(stacked: nn.Module, run: int) -> dict[str, Tensor]:
    """Run ``run``'s weights of a :func:`stack_runs` module as the state dict of a single-run module."""
    return {k: v[run].detach().clone() for k, v in stacked.state_dict().items()}


class GroupMLP(nn.Module):
    """ReLU MLP of ``GroupLinear`` layers; the last layer is linear (Q-values or message logits).

    ``norm`` layer-normalises each hidden pre-activation without a learned scale or shift: no parameters, so stacked
    runs need nothing extra, and the next layer's weights can rescale what they need.
    """

    def __init__(
        self, groups: int, in_features: int, hidden: tuple[int, ...], out_features: int, norm: bool = False
    ) -> None:
        super().__init__()
        sizes = [in_features, *hidden, out_features]
        self.layers = nn.ModuleList(GroupLinear(groups, a, b) for a, b in itertools.pairwise(sizes))
        self.norm = norm

    def forward(self, x: Tensor) -> Tensor:
        for layer in self.layers[:-1]:
            x = layer(x)
            if self.norm:
                x = F.layer_norm(x, x.shape[-1:])
            x = torch.relu(x)
        out: Tensor = self.layers[-1](x)  # torch leaves a module call untyped
        return out


def with_agent_id(x: Tensor, shared: bool) -> Tensor:
    """Append a one-hot agent id when parameters are shared, so one network can still tell agents apart."""
    if not shared or x.shape[-2] == 1:
        return x
    n = x.shape[-2]
    eye = torch.eye(n, device=x.device, dtype=x.dtype).expand(*x.shape[:-2], n, n)
    return torch.cat([x, eye], dim=-1)


def id_width(n_agents: int, shared: bool) -> int:
    """Extra input width ``with_agent_id`` adds."""
    return n_agents if shared and n_agents > 1 else 0


def message_bits(
    logits: Tensor,
    bits: int,
    train: bool,
    tau: float = 1.0,
    noise: float = 1.0,
    bound: float | None = None,
    rand: Callable[[Tensor], Tensor] = torch.rand_like,
) -> Tensor:
    """Discrete binary messages from logits ``[..., bits·2]`` → ``[..., bits]`` in {0, 1}.

    Training uses the straight-through Gumbel-softmax: the forward value is the hard one-hot of
    ``argmax(logits + noise·g)`` (g Gumbel), the gradient that of ``softmax((logits + noise·g) / tau)``. ``noise = 1``
    is the standard estimator (a message is *sampled*, so the listener trains on the speaker's uncertainty);
    ``noise = 0`` is the deterministic straight-through estimator. Execution takes the argmax, so what travels is
    exactly ``bits`` bits. ``rand`` draws the uniforms behind the noise (an agent passes its own generators, so a
    run's message noise depends on its seed alone).

    ``bound`` keeps each bit's logit difference in (−bound, bound) with ``bound · tanh(d / bound)``. Unbounded, the TD
    gradient drives the differences to |10–22|: every bit then takes one value on every observation and the
    straight-through gradient, ~e^−|d|, can never reopen the channel. Bounded, a bit stays a little noisy in training
    (the Gumbel pair's difference is logistic noise) and its gradient never vanishes.
    """
    if not train:
        return (bit_logits(logits, bits) > 0).to(logits.dtype)
    diff = bit_logits(logits, bits, bound)
    if noise > 0:  # the difference of two Gumbel draws is logistic: one draw per bit
        u = rand(diff).clamp_(1e-7, 1.0 - 1e-7)
        diff = diff + noise * (torch.log(u) - torch.log1p(-u))
    soft = torch.sigmoid(diff / tau)  # = softmax(pairs / tau)[..., 1]; softmax over a last dim of 2 is ~10× slower
    hard = (diff > 0).to(logits.dtype)
    return hard + (soft - soft.detach())  # exactly 0/1 forward (x − x = 0), the soft gradient backward


def bit_logits(logits: Tensor, bits: int, bound: float | None = None) -> Tensor:
    """Each bit's logit difference ``[..., bits]`` (P(bit = 1) = sigmoid of it), bounded by ``bound·tanh(d/bound)``."""
    pairs = logits.reshape(*logits.shape[:-1], bits, 2)
    diff = pairs[..., 1] - pairs[..., 0]
    return diff if bound is None else bound * torch.tanh(diff / bound)


def channel_information(diff: Tensor, runs: int = 1) -> Tensor:
    """A batch estimate of I(observation; message) in nats per sender: H(message) − H(message | observation).

    ``diff [..., S, bits]`` are the senders' bit logits over a batch of M observations (all leading dims). H(message |
    observation) is exact, Σ_bits H(p). H(message) is estimated on whole codewords: each observation's most likely
    codeword c_n is scored under the batch's mixture of channels, −mean_n log (1/M) Σ_m P(c_n | o_m). This is the
    positive-signalling objective of Eccles et al. (2019), which keeps a message informative while the TD gradient
    alone lets it collapse onto one codeword. Estimated bit by bit instead, it counts a bit copied 16 times as 16
    bits, and long runs ended with 16 copies of one split (message entropy ≈ ln 2).

    The first dim is the run axis, ``runs`` = R, and each run gets its own estimate ``[R]``.
    """
    d = diff.reshape(runs, -1, *diff.shape[-2:]).transpose(1, 2)  # [R, S, M, bits]
    log_p, log_q = F.logsigmoid(d), F.logsigmoid(-d)  # log P(bit = 1), log P(bit = 0)
    cond = (-(log_p.exp() * log_p + log_q.exp() * log_q)).sum(dim=-1).mean(dim=-1)  # [R, S]
    code = (d > 0).to(d.dtype)  # each observation's most likely codeword
    log_lik = code @ log_p.transpose(-1, -2) + (1 - code) @ log_q.transpose(-1, -2)  # [R, S, n, m]: log P(c_n | o_m)
    marginal = -(torch.logsumexp(log_lik, dim=-1) - math.log(d.shape[2])).mean(dim=-1)  # [R, S]
    return (marginal - cond).mean(dim=-1)


def signalling_loss(
    logits: Tensor, bits: int, cfg: GumbelConfig, runs: int = 1
) -> tuple[Tensor | None, dict[str, float | Tensor]]:
    """−signalling_coef × I(observation; message) from a batch's message logits ``[R, …]`` (None when the term is
    off), per run ``[R]``."""
    if not cfg.signalling_coef:
        return None, {}
    info = channel_information(bit_logits(logits, bits, cfg.message_logit_bound), runs)
    return -cfg.signalling_coef * info, {"message_info": info.detach()}


def gumbel_bits(
    logits: Tensor, bits: int, train: bool, cfg: GumbelConfig, rand: Callable[[Tensor], Tensor] = torch.rand_like
) -> Tensor:
    """``message_bits`` with the temperature, noise and logit bound of an algorithm's (resolved) config."""
    noise = resolved(cfg.gumbel_noise, "gumbel_noise")
    return message_bits(logits, bits, train, cfg.gumbel_tau, noise, cfg.message_logit_bound, rand)


def others_index(n_agents: int) -> Tensor:
    """``[N, N−1]`` indices of every agent's peers in order (agent i's row skips i)."""
    rows = [[j for j in range(n_agents) if j != i] for i in range(n_agents)]
    return torch.tensor(rows, dtype=torch.long).reshape(n_agents, max(n_agents - 1, 0))


def gather_others(x: Tensor, index: Tensor) -> Tensor:
    """Per agent, the concatenation of the other agents' vectors: ``[..., N, F]`` → ``[..., N, (N−1)·F]``."""
    picked = x[..., index, :]  # [..., N, N-1, F]
    return picked.reshape(*x.shape[:-2], index.shape[0], index.shape[1] * x.shape[-1])
