"""The entity encoder (``encoder=entity``): an observation read as a set of cars, not as a row of slots.

An MLP over the flat observation gives every slot its own weights: the same car reads differently in sensor slot 1,
in slot 3 or among the sightings teammates tell, and which slot a car lands in is one more thing to learn. Here one
per-car encoder φ reads every car alike — seen by the agent's own sensor or told by a teammate — and, for the
MA-MeSN / MA-BoN listeners, every heard message is one more entity (a message is a thing known about the world, like
a seen car) through its own embedding ψ; so is every word of a fixed code the env appends (``team_words``), through
ψ_w. A masked sum and a masked max pool them:

    Q_i = head([ρ(own_i, id_i), Σ_e m_e·φ(t_e), max_e m_e·φ(t_e)])      m_e = 1 for a car present, 0 for an empty slot

With ``entity_context`` φ reads ``[t_e, own_i]``: whether a car is on a collision course depends on the agent's own
heading and speed as much as on the car's, and after the pooling the head sees only a sum and a max over the cars, so
φ alone can pair each car with the agent's motion. The own features are the same for every car, so the pooled result
is still independent of slot order.

Why sum and max rather than one attention query from the own state: the sum keeps how many cars are near (a softmax
average forgets it), the max keeps the most extreme car on every feature however many harmless ones surround it
(the chaser behind), neither needs a softmax or query/key projections (cheaper), and as φ ends in a ReLU (φ ≥ 0),
m_e·φ makes an empty slot add exactly nothing to either.

A car's token, from the env's ``ObsLayout`` (no column number here is the treadmill's): ``[present, dx, dy, speed,
heading one-hot, heading known, adversary, adversary known, source one-hot (sensor, told)]``, offsets in the agent's
own frame. All tokens of all blocks come from one ``index_select`` of the flat observation and one multiply; an empty
slot's token is all zeros. The message embedding ψ is its own network, so a message needs no source flag: a
constant input would only repeat ψ's first bias.

Every layer is a ``GroupLinear`` (in a ``GroupMLP``) and every other op is parameter-free, so a population stacks its
runs (``stack_runs``) as it does the flat MLPs.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.nets import GroupMLP
from convoy.config import BoNConfig, ConfigError, IDQNConfig, MeSNConfig
from convoy.envs.batched import ENTITY_SOURCES, EnvSpec, ObsLayout
from convoy.envs.layout import entity_layout


def token_features(layout: ObsLayout) -> int:
    """Width of a car's token: present, dx, dy, speed, heading one-hot, heading known, adversary, adversary known,
    source one-hot."""
    return 4 + layout.headings + 3 + len(ENTITY_SOURCES)


def token_plan(layout: ObsLayout) -> tuple[list[int], list[float]]:
    """Per token feature, the observation column it copies and a factor (0 where the block does not give it):
    ``token = obs[index] · scale``. The flags (known, source) copy the present column, so an empty slot is zeros."""
    index: list[int] = []
    scale: list[float] = []
    for block in layout.cars:
        for slot in range(block.count):
            base = block.start + slot * block.width

            def col(c: int | None, base: int = base) -> tuple[int, float]:
                return (0, 0.0) if c is None else (base + c, 1.0)

            present, absent = col(block.present), col(None)
            heading = block.heading
            row = [
                present,
                col(block.dx),
                col(block.dy),
                col(block.speed),
                *(col(None if heading is None else heading + h) for h in range(layout.headings)),
                absent if heading is None else present,
                col(block.adversary),
                absent if block.adversary is None else present,
                *(present if block.source == source else absent for source in ENTITY_SOURCES),
            ]
            index += [i for i, _ in row]
            scale += [s for _, s in row]
    return index, scale


class EntityEncoder(nn.Module):
    """``[..., N, obs | extra | heard]`` → ``[..., N, 3·width]``: the own embedding ρ, then the sum and the max of
    the entities' embeddings. ``extra`` columns after the observation (the agent id, a fingerprint) join the own
    features; ``senders × bits`` columns after them are heard messages, one entity each."""

    index: Tensor  # [T·F] observation columns of every token feature
    scale: Tensor  # [T, F]

    def __init__(
        self,
        layout: ObsLayout,
        obs_dim: int,
        groups: int,
        extra: int,
        width: int,
        norm: bool,
        senders: int = 0,
        bits: int = 0,
        context: bool = False,
    ) -> None:
        super().__init__()
        index, scale = token_plan(layout)
        features = token_features(layout)
        # not in the state dict: derived from the layout, and a population's state is per run
        self.register_buffer("index", torch.tensor(index, dtype=torch.long), persistent=False)
        self.register_buffer("scale", torch.tensor(scale).reshape(-1, features), persistent=False)
        self.obs_dim, self.own_width, self.extra = obs_dim, layout.own, extra
        self.senders, self.bits = senders, bits
        self.own = GroupMLP(groups, layout.own + extra, (), width)  # ρ
        self.context = context
        self.car = GroupMLP(groups, features + (layout.own if context else 0), (width,), width, norm=norm)  # φ
        self.heard = GroupMLP(groups, bits, (width,), width, norm=norm) if senders else None  # ψ
        # an env's fixed-code words (team_words): entities through their own ψ_w, as heard messages through ψ
        self.words = layout.words
        self.word = GroupMLP(groups, self.words.bits, (width,), width, norm=norm) if self.words else None  # ψ_w
        self.out_features = 3 * width

    def tokens(self, x: Tensor) -> Tensor:
        """Every car's token ``[..., T, N, F]`` (agents on dim −2, as ``GroupLinear`` reads them)."""
        picked: Tensor = x.index_select(-1, self.index).unflatten(-1, tuple(self.scale.shape))  # [..., N, T, F]
        return (picked * self.scale).transpose(-3, -2)

    def cars(self, x: Tensor) -> Tensor:
        """Every car's m·φ ``[..., T, N, width]``: φ reads its token (with ``context``, beside the agent's own
        features); an empty slot is 0, so it adds nothing to the sum or the max."""
        tokens = self.tokens(x)
        read = tokens
        if self.context:
            own = x[..., : self.own_width].unsqueeze(-3).expand(*tokens.shape[:-1], self.own_width)
            read = torch.cat([tokens, own], dim=-1)
        return F.relu(self.car(read)) * tokens[..., :1]

    def forward(self, x: Tensor) -> Tensor:
        entities = self.cars(x)
        end = self.obs_dim + self.extra
        if self.heard is not None:
            entities = torch.cat([entities, said(x, end, self.senders, self.bits, self.heard)], dim=-3)
        if self.word is not None and self.words is not None:
            w = self.words
            entities = torch.cat([entities, said(x, w.start, w.count, w.bits, self.word)], dim=-3)
        own = torch.cat([x[..., : self.own_width], x[..., self.obs_dim : end]], dim=-1)
        return torch.cat([F.relu(self.own(own)), entities.sum(dim=-3), entities.amax(dim=-3)], dim=-1)


def said(x: Tensor, start: int, count: int, bits: int, embed: nn.Module) -> Tensor:
    """``count`` words of ``bits`` columns from column ``start`` of ``x [..., N, D]``, each one entity through
    ``embed``: ``[..., count, N, width]``."""
    words = x[..., start : start + count * bits].unflatten(-1, (count, bits)).transpose(-3, -2)  # [..., S, N, bits]
    return F.relu(embed(words))


class Dueling(nn.Module):
    """``[..., 1 + A]`` → ``Q [..., A]``: Q_a = V + A_a − mean_b A_b (Wang et al. 2016). Parameter-free, so the layer
    before it stacks runs like any other."""

    def forward(self, x: Tensor) -> Tensor:
        value, advantage = x[..., :1], x[..., 1:]
        return value + advantage - advantage.mean(dim=-1, keepdim=True)


class Heads(nn.Module):
    """``[..., F]`` → ``[..., K, out]``: K heads, the K groups of one ``GroupMLP``, each reading the same features
    (Bootstrapped DQN's heads on a shared torso: one batched matmul for all of them)."""

    def __init__(self, heads: int, mlp: GroupMLP) -> None:
        super().__init__()
        self.heads, self.mlp = heads, mlp

    def forward(self, x: Tensor) -> Tensor:
        out: Tensor = self.mlp(x.unsqueeze(-2).expand(*x.shape[:-1], self.heads, x.shape[-1]))
        return out


def obs_network(
    spec: EnvSpec,
    cfg: IDQNConfig | MeSNConfig | BoNConfig,
    groups: int,
    extra: int,
    hidden: tuple[int, ...],
    out: int,
    senders: int = 0,
    bits: int = 0,
    q_values: bool = False,
    heads: int = 1,
) -> nn.Module:
    """The network reading ``[obs | extra | heard]`` (``extra`` columns, ``senders × bits`` heard) into ``out``
    values: one MLP over the flat columns (``encoder=mlp``), or the entity encoder and an MLP head on its pooled
    features, both of ``hidden`` widths. ``q_values``: the outputs are Q-values, formed by a dueling head when
    ``cfg.dueling``. ``heads`` > 1 (shared weights only): that many MLPs on one encoder (the flat observation for
    ``mlp``), ``[..., N, heads, out]``."""
    dueling = q_values and cfg.dueling
    width = out + 1 if dueling else out

    def head(features: int) -> nn.Module:
        if heads == 1:
            return GroupMLP(groups, features, hidden, width, norm=cfg.layer_norm)
        if groups != 1:
            raise ConfigError("heads", f"{heads} heads need one network for every agent; set share_params=true")
        return Heads(heads, GroupMLP(heads, features, hidden, width, norm=cfg.layer_norm))

    if cfg.encoder == "mlp":
        net: nn.Module = head(spec.obs_dim + extra + senders * bits)
    else:
        layout = entity_layout(spec)
        enc = EntityEncoder(
            layout, spec.obs_dim, groups, extra, cfg.entity_width, cfg.layer_norm, senders, bits, cfg.entity_context
        )
        net = nn.Sequential(enc, head(enc.out_features))
    return nn.Sequential(net, Dueling()) if dueling else net
