"""One update of a network agent: the pieces every value learner's loss is made of, and the guarded step that
follows it. With the algorithm's own file (its networks and ``loss``, in its paper's order) this is all one update
reads: ``NetworkAgent.update`` is ``updater.update(sample())``.

* The loss's pieces: the taken actions' Q (``taken``), the double-Q TD target (``td_target``, ``bootstrap_target``),
  the TD loss (``td_loss``) and what a loss returns (``Loss``).
* :class:`Updater`: gradients of the summed loss, each run's clip, the non-finite guard, Adam with one learning rate
  per run (``RunAdam``), the Polyak target and policy average, the periodic target sync, the figures (left on the
  device, ``StepFigures``) and the checkpoint state of all of it, per run.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, overload

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from convoy.algos.nets import run_state
from convoy.algos.streams import RunStreams, legacy_counter
from convoy.config import AlgoConfig
from convoy.transition import Transition

# Updates in a row whose loss or gradient is not finite before the run fails: one is skipped (a bad batch), this
# many means the weights or the data are broken and going on would only hide it. Checked when the figures are read
# (``Figures``), not in the update: the trainer reads them every ``READ_EVERY`` updates (learner/core.py).
MAX_NONFINITE_IN_A_ROW = 100
NEG = -1e9  # Q-value given to actions an agent does not have (heterogeneous action spaces)

Batch = Transition[Tensor]  # a sampled batch [R, M, …] (DIAL's sequences [R, T, B, …]), on the device
QFn = Callable[[nn.ModuleDict, Tensor], Tensor]  # (networks, observations [M, N, D]) → Q [M, N, A]


class Loss(NamedTuple):
    """What one batch costs: each agent's loss ``[N]`` (their sum is minimised), an auxiliary term trained on the
    same batch (positive signalling, a memory module's message prediction) and figures to report."""

    agents: Tensor  # [R, N]
    extra: Tensor | None = None  # [R]
    stats: dict[str, float | Tensor] = {}  # noqa: RUF012  (a NamedTuple default, never mutated)
    priority: Tensor | None = None  # [R, M]: each sample's |TD error|, for prioritized replay

    def plus(self, extra: Tensor | None, stats: Mapping[str, float | Tensor]) -> Loss:
        """This loss with one more auxiliary term and its figures."""
        total = self.extra if extra is None else extra if self.extra is None else self.extra + extra
        return Loss(self.agents, total, {**self.stats, **stats}, self.priority)


def taken(q: Tensor, action: Tensor) -> Tensor:
    """Q of the actions taken: ``[..., N, A]`` → ``[..., N]``."""
    return q.gather(-1, action.unsqueeze(-1)).squeeze(-1)


def td_target(
    reward: Tensor,
    terminated: Tensor,
    gamma: float | Tensor,
    q_next_target: Tensor,
    q_next_online: Tensor | None,
    mask: Tensor,
) -> Tensor:
    """``r + γ (1 − terminated) Q_target(s', a*)`` with ``a*`` the online argmax (double Q) or the target's.

    ``gamma`` may be one discount per sample ``[M]``: a transition that spans τ steps (an option of hierarchical
    DQN) bootstraps with γ^τ, or options that collect more steps of reward would look better for that alone.
    """
    target_q = q_next_target.masked_fill(~mask, NEG)
    if q_next_online is None:
        best = target_q.max(dim=-1).values
    else:
        a_star = q_next_online.masked_fill(~mask, NEG).argmax(dim=-1, keepdim=True)
        best = target_q.gather(-1, a_star).squeeze(-1)
    cont = (1.0 - terminated.float()).unsqueeze(-1)
    if isinstance(gamma, Tensor):
        gamma = gamma.unsqueeze(-1)
    return reward + gamma * cont * best


class Bootstraps(Protocol):
    """What the TD target reads of an agent: its online and target networks, the actions each agent has and its
    discount and advantage-learning weight (a population's: one per run, ``[R, 1]`` and ``[R, 1, 1]``)."""

    online: nn.ModuleDict
    target: nn.ModuleDict
    action_mask: Tensor  # [N, A]
    gamma: float | Tensor
    alpha: float | Tensor

    @property
    def cfg(self) -> AlgoConfig: ...


@torch.no_grad()
def bootstrap_target(agent: Bootstraps, q_fn: QFn, batch: Batch) -> Tensor:
    """The TD target ``[M, N]`` of a batch for any ``q_fn``: the target networks' Q at the next observation, the
    action picked by the online networks (``double_q``), a per-sample ``discount`` when stored (n-step returns,
    options), and advantage learning's action gap ``max_b Q̄(s, b) − Q̄(s, a)`` subtracted when
    ``advantage_learning`` > 0."""
    mask = agent.action_mask
    q_next_t = q_fn(agent.target, batch.next_obs)
    q_next_o = q_fn(agent.online, batch.next_obs) if agent.cfg.double_q else None
    discount = batch.extras.get("discount", agent.gamma)
    y = td_target(batch.reward, batch.terminated, discount, q_next_t, q_next_o, mask)
    if isinstance(agent.alpha, Tensor) or agent.alpha:
        q_now = q_fn(agent.target, batch.obs)
        gap = q_now.masked_fill(~mask, NEG).max(dim=-1).values - taken(q_now, batch.action)
        y = y - agent.alpha * gap
    return y


DQFD_MARGIN = 0.8  # DQfD's l(a_E, a) for every action but the demonstrator's (Hester et al. 2018)


def large_margin(q: Tensor, expert: Tensor, mask: Tensor) -> Tensor:
    """DQfD's supervised loss ``max_a [Q(s, a) + l(a_E, a)] − Q(s, a_E)`` per run: the demonstrator's action must
    lead every other Q-value by ``DQFD_MARGIN``, and once it does the term asks nothing more of the values, which
    TD goes on setting. ``q [R, b, N, A]``, ``expert [R, b, N]``, ``mask [N, A]`` (actions each agent has) → ``[R]``."""
    margins = torch.full_like(q, DQFD_MARGIN).scatter(-1, expert.unsqueeze(-1), 0.0)
    best = (q + margins).masked_fill(~mask, NEG).amax(dim=-1)
    return (best - taken(q, expert)).mean(dim=(-2, -1))


def td_loss(q: Tensor, y: Tensor, cfg: AlgoConfig) -> Tensor:
    """Elementwise TD loss: Huber (clipped error) or the paper's squared error, per the ``huber`` switch."""
    return F.smooth_l1_loss(q, y, reduction="none") if cfg.huber else 0.5 * (q - y) ** 2


class Updater:
    """One agent's learning step and the state it keeps between steps, for R ≥ 1 runs at once: Adam with one
    learning rate per run (made on first use: actors never update), the non-finite guard's counters on the device,
    the target sync and each run's checkpoint state. ``loss`` is the algorithm's; the networks are the algorithm's
    too (``online`` is what Adam steps, ``target`` and ``average`` what the step and the sync move)."""

    def __init__(
        self,
        name: str,
        seeds: tuple[int, ...],
        nets: tuple[nn.ModuleDict, nn.ModuleDict, nn.ModuleDict | None],
        streams: dict[str, RunStreams],
        loss: Callable[[Batch], Loss],
        configs: Sequence[AlgoConfig],
        syncs_by_updates: bool = True,
    ) -> None:
        """``nets``: (online, target, average or None); ``syncs_by_updates``: the target follows the update count
        (DIAL syncs by finished episodes instead, ``sync_runs``; behaviour cloning has no target)."""
        self.name, self.seeds, self.streams, self.loss = name, seeds, streams, loss
        self.online, self.target, self.average = nets
        self.syncs_by_updates = syncs_by_updates
        self.device = next(iter(streams.values())).counters.device
        self.updates = 0  # update() calls, a skipped one too (whether a run skipped is known on the device only)
        # on the device, so that no update reads them: updates with a run whose loss or gradient was not finite
        # (``skipped_updates``), and each run's count of them in a row (read with the figures)
        self._skipped = torch.zeros((), dtype=torch.int64, device=self.device)
        self._nonfinite_in_a_row = torch.zeros(len(seeds), dtype=torch.int64, device=self.device)
        self._optimizer: RunAdam | None = None
        self._compiled: Callable[[Batch], tuple[tuple[str, ...], Tensor, Tensor | None]] | None = None
        self.priority: Tensor | None = None  # the last update's per-sample |TD error| [R, M], if its loss gave one
        self.set_run_configs(configs)

    def set_run_configs(self, configs: Sequence[AlgoConfig]) -> None:
        """Each run's learning rate schedule and target period (``NetworkAgent.set_run_configs`` checks the rest)."""
        if self._optimizer is not None:
            raise RuntimeError("set_run_configs: call it before the first update")
        self.run_cfgs, self.cfg = list(configs), configs[0]
        periods = [c.target_update for c in configs]
        self._periods = None if len(set(periods)) == 1 else torch.tensor(periods, device=self.device)

    @property
    def skipped_updates(self) -> int:
        """Updates in which some run's loss or gradient was not finite (that run took no step); a host read."""
        return int(self._skipped)

    @skipped_updates.setter
    def skipped_updates(self, value: int) -> None:
        self._skipped.fill_(value)

    @property
    def optimizer(self) -> RunAdam:
        """Adam with one learning rate per run on the device (:class:`RunAdam`), made on first use: actors never
        update, and the first optimizer of a process costs ~2 s of imports."""
        if self._optimizer is None:
            lrs = torch.tensor([c.lr for c in self.run_cfgs], device=self.device)
            ends = torch.tensor([lr_at(c, 1, 1) for c in self.run_cfgs], device=self.device)  # at the run's end
            self._optimizer = RunAdam(list(self.online.parameters()), lrs, ends)
        return self._optimizer

    def update(self, batch: Batch, fraction: float) -> Figures:
        """One gradient step on ``batch`` (the agents' losses summed, plus any auxiliary term) with each run's
        learning rate ``fraction`` of the way through its schedule (``lr_end``), then the target sync; the figures
        stay on the device (``Figures``: ``read()`` them, or let the trainer read them in batches). Nothing in the
        update waits for the device: a non-finite loss or gradient is caught by a mask on the device and never
        reaches the weights, and the run fails (``FloatingPointError``) when figures that counted
        ``MAX_NONFINITE_IN_A_ROW`` such updates in a row are read, so at most one read interval late (``READ_EVERY``
        updates in the trainer).

        A population takes one step for all runs: their losses are summed (no weight is shared between runs, so
        each run's gradient is its own loss's), each run's gradient is clipped to its own norm, and a run whose
        loss or gradient is not finite keeps its weights, target, Adam moments and step count while the others
        step. ``updates`` counts every call, skipped or not: the host cannot know without a read. With ``compile``
        the step from the batch on runs as one captured graph (``torch.compile(fullgraph=True)``).
        """
        if any(c.lr_end is not None for c in self.run_cfgs):  # one op on the device; none at constant lr
            self.optimizer.anneal(fraction)
        names, table, self.priority = self._compiled_step(batch) if self.cfg.compile else self._step(batch)
        self.updates += 1
        if self.syncs_by_updates:
            self.sync_targets()
        return StepFigures(self.name, self.seeds, names, table)

    def _compiled_step(self, batch: Batch) -> tuple[tuple[str, ...], Tensor, Tensor | None]:
        """``_step`` compiled whole on first use (no graph break: a break is an error). On CUDA the graph is also
        captured as a CUDA graph (``cuda_graph_options``): one launch per update instead of one per kernel.
        A CUDA graph replays fixed addresses, so the state the step writes in place (Adam's moments and counts, the
        learning rates, the guard's counters, the noise streams' counters) is marked static, and the figures are
        copied out: the next replay overwrites its outputs, and figures are read many updates later."""
        cuda = self.device.type == "cuda"
        if self._compiled is None:
            opt = self.optimizer  # made before tracing: its state is the graph's input, not built in it
            if cuda:
                mutated = [*opt._m, *opt._v, opt._steps, opt.lrs, self._skipped, self._nonfinite_in_a_row]
                for t in mutated + [s.counters for s in self.streams.values()]:
                    torch._dynamo.mark_static_address(t)
            self._compiled = torch.compile(self._step, fullgraph=True, options=cuda_graph_options() if cuda else None)
        with torch._dynamo.config.patch(trace_autograd_ops=True):  # autograd.grad inside the graph
            names, table, priority = self._compiled(batch)
        if cuda:
            table, priority = table.clone(), None if priority is None else priority.clone()
        return names, table, priority

    def _step(self, batch: Batch) -> tuple[tuple[str, ...], Tensor, Tensor | None]:
        """Loss → gradients → each run's clip → the non-finite guard → Adam → Polyak target and policy average,
        all on the device. Returns the figures' names, their table (``StepFigures``) and the loss's per-sample
        priorities (or None)."""
        out = self.loss(batch)
        loss = out.agents.sum(dim=-1)  # [] or [R]
        total = loss.sum() if out.extra is None else loss.sum() + out.extra.sum()
        params = self.optimizer.params
        raw = torch.autograd.grad(total, params, allow_unused=True)
        # a weight no loss reaches (a cut channel's message net) gets a zero gradient: Adam then leaves it as it is
        grads = [torch.zeros_like(p) if g is None else g.contiguous() for p, g in zip(params, raw, strict=True)]
        grad_norm = clip_grad_norm_per_run(grads, self.cfg.grad_clip)
        ok = torch.isfinite(loss) & torch.isfinite(grad_norm)  # [] or [R]: which runs step
        self.optimizer.step_runs(grads, ok)
        with torch.no_grad():
            skipped = ~ok
            self._skipped.add_(skipped.any())
            self._nonfinite_in_a_row.add_(1).mul_(skipped)
            if self.syncs_by_updates and self.cfg.target_tau < 1.0:
                polyak_(self.target, self.online, self.cfg.target_tau * ok.float())
            if self.average is not None:
                polyak_(self.average, self.online, self.cfg.policy_ema * ok.float())
            # a figure given as a float is filled in on the device (a tensor made from it would be a host copy)
            stats = [v.float().expand_as(loss) if isinstance(v, Tensor) else torch.full_like(loss, v)
                     for v in out.stats.values()]  # fmt: skip
            table = torch.stack([loss.detach(), grad_norm, *stats, self._nonfinite_in_a_row.float()])
            priority = None if out.priority is None else out.priority.detach()
        return ("loss", "grad_norm", *out.stats), table.reshape(table.shape[0], -1), priority

    def sync_targets(self) -> None:
        """After an update: copy the online weights into the target of every run whose ``target_update`` period
        the update count has reached. The count is the host's, so this ``if`` reads nothing from the device and
        stays outside the compiled step; runs with their own periods are picked by a 0/1 mask made on the device.
        Polyak targets (``target_tau`` < 1) move in the step itself."""
        if self.cfg.target_tau < 1.0 or not any(self.updates % c.target_update == 0 for c in self.run_cfgs):
            return
        if self._periods is None:  # every run is due
            with torch.no_grad():
                torch._foreach_copy_(list(self.target.parameters()), list(self.online.parameters()))
        else:
            polyak_(self.target, self.online, (torch.remainder(self.updates, self._periods) == 0).float())

    def sync_runs(self, due: np.ndarray) -> None:
        """Copy the online weights into the target of the runs ``due`` (runs that sync apart, DIAL's)."""
        idx = torch.as_tensor(np.flatnonzero(due), device=self.device)
        with torch.no_grad():
            for t, o in zip(self.target.parameters(), self.online.parameters(), strict=True):
                t.index_copy_(0, idx, o.index_select(0, idx))

    # --- checkpoint state: a run's, without the run axis ----------------------------------------------------------
    def run_state_dict(self, k: int) -> dict[str, Any]:
        """Run k's networks, targets, Adam state, update count and random streams as a single run's: every tensor
        without the run axis (the layout checkpoints have always had)."""
        opt = self.optimizer.state_dict()
        moments = {i: {n: v[k].clone() for n, v in st.items()} for i, st in opt["state"].items()}  # step: run k's
        return {
            "online": run_state(self.online, k),
            "target": run_state(self.target, k),
            **({} if self.average is None else {"average": run_state(self.average, k)}),
            "optimizer": {"param_groups": opt["param_groups"], "state": moments},
            "updates": self.updates,
            "streams": self.stream_state(k),
        }

    def stream_state(self, k: int) -> dict[str, int]:
        """Run k's random streams: the seed they are keyed by and each purpose's counter (``algos.streams``)."""
        streams = self.streams.values()
        return {"seed": next(iter(streams)).seeds[k], **{s.stream: s.state(k) for s in streams}}

    def load_run_state(self, k: int, state: dict[str, Any]) -> None:
        """Put a single run's state (``run_state_dict``, a checkpoint's: no run axis) into run k."""
        opt = self.optimizer
        with torch.no_grad():
            modules = [(self.online, "online"), (self.target, "target")]
            if self.average is not None:
                modules.append((self.average, "average" if "average" in state else "online"))
            for module, key in modules:
                for name, value in module.state_dict().items():
                    value[k].copy_(state[key][name])
            for i, st in state["optimizer"]["state"].items():  # a single run's Adam state (torch.optim.Adam's too)
                for n, v in st.items():
                    opt.state[opt.params[int(i)]][n][k].copy_(v)
        self.updates = int(state["updates"])
        self.load_streams(k, state)

    def load_streams(self, k: int, state: dict[str, Any]) -> None:
        """Run k's streams from a single run's state. A checkpoint written before the device streams holds numpy
        and torch generator states instead ("rng", "torch_rng", DIAL's "dru_rng"): its streams start at
        ``legacy_counter(seed, updates)``, so such a resumed run draws other numbers than the old code would have
        (another generator), though the same ones at every resume of that file."""
        saved = state.get("streams")
        for name, stream in self.streams.items():
            if saved is None:
                stream.load(k, legacy_counter(stream.seeds[k], int(state["updates"])))
            else:
                stream.load(k, saved[name], saved["seed"])


def clip_grad_norm_per_run(grads: list[Tensor], max_norm: float) -> Tensor:
    """Each run's gradient ``[R, …]`` scaled in place to at most ``max_norm`` (``clip_grad_norm_`` per run); the
    norms before the clip ``[R]``. One run's norm is summed as ``clip_grad_norm_`` sums it, bit for bit."""
    if grads[0].shape[0] == 1:
        total: Tensor = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads))).reshape(1)
    else:
        norms = torch.stack([torch.linalg.vector_norm(g.flatten(1), dim=1) for g in grads])  # [params, R]
        total = torch.linalg.vector_norm(norms, dim=0)  # [R]
    coef = (max_norm / (total + 1e-6)).clamp(max=1.0)
    torch._foreach_mul_(grads, [per_run(coef, g) for g in grads])
    return total


class RunAdam(torch.optim.Optimizer):
    """Adam (torch's defaults: β = (0.9, 0.999), ε = 1e-8) over R ≥ 1 runs' stacked parameters ``[R, …]``,
    with one learning rate per run on the device (``lrs``, annealed there) and a per-run ``ok`` mask
    (``step_runs``): a run not ok keeps its weights, moments and step count, with no host read.

    Its state has ``torch.optim.Adam``'s layout, ``step``, ``exp_avg`` and ``exp_avg_sq`` per parameter, made up
    front (a compiled step never branches on it), with a leading run axis (``step`` one count per run ``[R]``): a
    run's share is a single run's state, and a single run's, or a checkpoint that ``torch.optim.Adam(fused=True)``
    wrote, loads into a run (``NetworkAgent.load_member_state``). Every parameter steps at every update (one a loss
    does not reach with a zero gradient), so all of them share one ``step`` tensor.

    Two kernels, one arithmetic (equal to ``torch.optim.Adam`` up to float rounding): a run of one steps with
    torch's fused Adam, one kernel whose ``found_inf`` skips the step on the device; R > 1 runs, and any step
    under ``torch.compile``, with ``torch._foreach_*`` ops whose per-run factors mask the step — the fused kernel
    takes one learning rate and one skip flag per call, so per-run ones would cost a call per run.
    """

    def __init__(
        self,
        params: list[Tensor],
        lrs: Tensor,
        ends: Tensor | None = None,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        super().__init__(params, {"lr": 0.0, "betas": betas, "eps": eps})  # the rates live in ``lrs``
        self.params: list[Tensor] = list(params)
        self.runs = len(lrs)
        self.lrs, self.start = lrs, lrs.clone()
        self.span = torch.zeros_like(lrs) if ends is None else ends - lrs  # to each run's ``lr_end`` by the run's end
        self._fill_state()

    def _fill_state(self) -> None:
        """Zero moments for every parameter without them, and one shared step count (the largest loaded)."""
        shape = (self.runs,)
        device = self.params[0].device
        counts = [self.state[p]["step"] for p in self.params if "step" in self.state[p]]
        step = torch.zeros(shape, dtype=torch.float32, device=device)
        if counts:
            step = torch.stack([c.to(device=device, dtype=torch.float32).reshape(shape) for c in counts]).amax(0)
        for p in self.params:
            st = self.state[p]
            st["step"] = step
            for name in ("exp_avg", "exp_avg_sq"):
                if name not in st:
                    st[name] = torch.zeros_like(p, memory_format=torch.preserve_format)
        self._steps = step
        self._m = [self.state[p]["exp_avg"] for p in self.params]
        self._v = [self.state[p]["exp_avg_sq"] for p in self.params]

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self._fill_state()

    def anneal(self, fraction: float) -> None:
        """Each run's rate ``fraction`` of the way to its end rate, computed on the device (no host copy)."""
        torch.add(self.start, self.span, alpha=fraction, out=self.lrs)

    @overload
    def step(self, closure: None = None) -> None: ...
    @overload
    def step(self, closure: Callable[[], float]) -> float: ...
    def step(self, closure: Callable[[], float] | None = None) -> float | None:  # the closure is never called
        """``torch.optim``'s step: every run, from the parameters' ``.grad``."""
        grads = [torch.zeros_like(p) if p.grad is None else p.grad for p in self.params]
        self.step_runs(grads, torch.ones_like(self._steps, dtype=torch.bool))
        return None

    @torch.no_grad()
    def step_runs(self, grads: Sequence[Tensor], ok: Tensor) -> None:
        """One Adam step of the runs with ``ok`` (``[R]``, or 0-dim for a single run) from ``grads`` (parameter
        order, used as scratch: a run not ok may hold NaN there)."""
        b1, b2 = self.defaults["betas"]
        eps: float = self.defaults["eps"]
        okf = ok.float()
        self._steps.add_(okf)
        params, m, v = self.params, self._m, self._v
        if self.runs == 1 and not torch.compiler.is_compiling():  # one run: torch's fused kernel, its rounding
            steps = self._steps.view(())
            torch._fused_adam_(params, list(grads), m, v, [], [steps] * len(params), lr=self.lrs.view(()),
                               beta1=b1, beta2=b2, weight_decay=0.0, eps=eps, amsgrad=False, maximize=False,
                               found_inf=(1.0 - okf).view(()))  # fmt: skip
            return

        def each(x: Tensor) -> list[Tensor]:  # one value per run, for every parameter
            return [per_run(x, p) for p in params]

        grads = list(grads)
        for g, bad in zip(grads, each(~ok), strict=True):
            g.masked_fill_(bad, 0.0)  # NaN·0 is NaN: a skipped run's gradient must go, not be scaled
        # m ← m + (1 − β1)(g − m), v ← β2·v + (1 − β2)·g², as the fused kernel rounds them; unchanged where not ok
        torch._foreach_lerp_(m, grads, each(torch.where(ok, 1 - b1, 0.0)))
        torch._foreach_mul_(v, each(torch.where(ok, b2, 1.0)))
        torch._foreach_addcmul_(v, grads, grads, value=1 - b2)
        # bias corrections in float64, as torch's kernels take them (1 − 0.999 in float32 is off by 6e-5); a run
        # never stepped counts 0, clamped: any correction will do, it moves by 0
        t = self._steps.double().clamp(min=1.0)
        bias1, bias2 = 1 - b1**t, (1 - b2**t).sqrt()
        size = self.lrs.double() * bias2 / bias1  # Δp = −size · m / (√v + ε·bias2), torch's step rearranged
        # the denominator over ``size``, in the gradients' memory: ∞ for a run not ok, whose step is then m / ∞ = 0
        scale = torch.where(ok, 1 / size, 0.0).float()
        offset = torch.where(ok, eps * bias2 / size, math.inf).float()
        for g, sq in zip(grads, v, strict=True):
            torch.sqrt(sq, out=g)
        torch._foreach_mul_(grads, each(scale))
        torch._foreach_add_(grads, each(offset))
        torch._foreach_addcdiv_(params, m, grads, value=-1.0)


def polyak_(average: nn.Module, online: nn.Module, tau: float | Tensor) -> None:
    """average ← (1 − τ)·average + τ·online, in place (the Polyak target and the averaged policy). ``tau`` may be a
    device tensor, one weight per run ``[R]`` (or 0-dim): 0 leaves a run as it is and 1 copies it exactly (lerp
    computes ``online − (online − average)·(1 − τ)`` for τ ≥ 0.5), so it is also a masked copy with no host read."""
    avg: list[Tensor] = list(average.parameters())
    new: list[Tensor] = list(online.parameters())
    with torch.no_grad():
        if isinstance(tau, Tensor):
            torch._foreach_lerp_(avg, new, [per_run(tau, p) for p in avg])
        else:
            torch._foreach_lerp_(avg, new, tau)


def per_run(x: Tensor, like: Tensor) -> Tensor:
    """One value per run ``[R]`` shaped to broadcast over a stacked tensor ``like [R, …]`` (a 0-dim one as it is)."""
    return x if x.dim() == 0 else x.reshape(-1, *([1] * (like.dim() - 1)))


def run_fraction(env_steps: int, total_steps: int) -> float:
    """How far the run has gone, 0 → 1 (held at 1 past its end)."""
    return min(1.0, env_steps / max(1, total_steps))


def lr_at(cfg: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """``lr`` annealed linearly to ``lr_end`` over the run (``lr`` throughout when ``lr_end`` is None)."""
    if cfg.lr_end is None:
        return cfg.lr
    return cfg.lr + run_fraction(env_steps, total_steps) * (cfg.lr_end - cfg.lr)


class Figures(ABC):
    """One update's figures (loss, gradient norm, the algorithm's own), left on the device where they were
    computed: reading them is a host sync, so an update never reads them and the trainer reads many updates' at
    once (:func:`read_figures`). Reading is also where a run that had ``MAX_NONFINITE_IN_A_ROW`` non-finite updates
    in a row fails, with a ``FloatingPointError``."""

    @abstractmethod
    def tensors(self) -> list[Tensor]:
        """The device tensors reading copies to the host."""

    @abstractmethod
    def rows(self, host: list[np.ndarray]) -> list[dict[str, float]]:
        """One dict of figures per run (a single run's: one) from the host copies of ``tensors()``."""

    def read(self) -> list[dict[str, float]]:
        """The figures, one host sync: one dict per run (a single run's: one)."""
        return read_figures([self])[0]


def read_figures(batch: Sequence[Figures]) -> list[list[dict[str, float]]]:
    """Many updates' figures in one host read, in update order: each update's one dict per run. Raises
    ``FloatingPointError`` at the first update that ends a run (``MAX_NONFINITE_IN_A_ROW``)."""
    tensors = [t for figures in batch for t in figures.tensors()]
    if not tensors:
        return [figures.rows([]) for figures in batch]
    flat = torch.cat([t.detach().reshape(-1).float() for t in tensors])
    values = np.asarray(flat.cpu(), dtype=np.float64)  # the one host sync
    host = np.split(values, np.cumsum([t.numel() for t in tensors])[:-1])
    out, i = [], 0
    for figures in batch:
        n = len(figures.tensors())
        out.append(figures.rows(host[i : i + n]))
        i += n
    return out


@dataclass(frozen=True)
class StepFigures(Figures):
    """A :class:`NetworkAgent` update's figures: ``table [len(names) + 1, R]`` (a single run's R = 1), the figures
    as computed (a skipped run's loss and gradient norm too, for the failure's message) and, last, each run's count
    of non-finite updates in a row up to this one (> 0: this update was skipped, its loss and norm read as NaN)."""

    agent: str  # the algorithm's name, for the failure's message
    seeds: tuple[int, ...]
    names: tuple[str, ...]
    table: Tensor

    def tensors(self) -> list[Tensor]:
        return [self.table]

    def rows(self, host: list[np.ndarray]) -> list[dict[str, float]]:
        table = host[0].reshape(len(self.names) + 1, -1)
        streak = table[-1]
        worst = int(np.argmax(streak))
        if streak[worst] >= MAX_NONFINITE_IN_A_ROW:
            raise FloatingPointError(
                f"{self.agent} (run of seed {self.seeds[worst]}): {int(streak[worst])} updates in a row had a "
                f"non-finite loss ({table[0, worst]}) or gradient norm ({table[1, worst]}); the weights were kept as "
                "they were. Check the env's rewards and observations for NaN/inf, or lower lr"
            )
        rows = [dict(zip(self.names, col, strict=True)) for col in table[:-1].T.tolist()]
        for row, skipped in zip(rows, streak > 0, strict=True):
            if skipped:
                row.update(loss=float("nan"), grad_norm=float("nan"))
        return rows


def cuda_graph_options() -> dict[str, Any]:
    """Inductor's options for the step on CUDA: replayed as a CUDA graph (what ``mode="reduce-overhead"`` sets),
    loop reordering after fusion off — torch 2.11's inductor asserts on the per-run Adam's foreach kernels there
    (seen on an H200; 2.13 does not), and it only tunes memory order inside fused kernels."""
    from torch._inductor import config  # imported when a step is compiled, not with the package

    return {"triton.cudagraphs": True, **{k: False for k in ("loop_ordering_after_fusion",) if hasattr(config, k)}}
