"""The update on the device: ``RunAdam`` is torch's Adam per run, an update reads nothing back to the host and
dispatches as many ops for 20 runs as for one, and ``compile`` captures it whole, equal to the eager update.

The op counts include sampling: the replay lives on the update's device and draws every run's indices at once
from the runs' counter streams (``algos/streams.py``).
"""

from __future__ import annotations

import copy
import math
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.nets import run_state
from convoy.algos.registry import make_algorithm
from convoy.algos.updater import MAX_NONFINITE_IN_A_ROW, RunAdam, read_figures
from tests.test_population import POPULATION_ALGOS, SEEDS, SPEC, chunk, config, save_teacher
from tests.transitions import run_of

SHAPES = [(2, 6, 5), (2, 5), (1, 5, 3)]
CUDA = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a CUDA device"
)  # GroupLinear-like weights and biases


class Dispatches(TorchDispatchMode):
    """Every ATen op dispatched inside the ``with``, by name."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        self.ops[str(func)] += 1
        return func(*args, **(kwargs or {}))


@contextmanager
def counting(monkeypatch: pytest.MonkeyPatch) -> Iterator[Dispatches]:
    """Ops dispatched, with host reads that bypass the dispatcher on a CPU (``numpy``, ``tolist``) counted as
    ``host:numpy`` / ``host:tolist``; ``aten._local_scalar_dense`` is what ``item``, ``float`` and ``bool`` run."""
    mode = Dispatches()
    for name in ("numpy", "tolist"):
        real = getattr(torch.Tensor, name)

        def read(self: torch.Tensor, *a: Any, _real: Callable[..., Any] = real, _name: str = name, **k: Any) -> Any:
            mode.ops[f"host:{_name}"] += 1
            return _real(self, *a, **k)

        monkeypatch.setattr(torch.Tensor, name, read)
    with mode:
        yield mode
    monkeypatch.undo()


def host_reads(ops: Counter[str]) -> dict[str, int]:
    return {op: n for op, n in ops.items() if "_local_scalar_dense" in op or op.startswith("host:")}


def filled(name: str, seeds: int | list[int], device: str = "cpu", **params: Any) -> NetworkAgent:
    """``name`` (small networks) with replay rows and its update's batch fixed (``sample`` returns it)."""
    cfg = config(name, False, hidden=(16,), batch_size=8, **params)
    agent = make_algorithm(name, SPEC, cfg, device=device, seed=seeds)
    g = np.random.default_rng(0)
    runs = len(seeds) if isinstance(seeds, list) else 1
    for _ in range(2):
        c = chunk(g, runs)
        agent.observe(c if isinstance(seeds, list) else run_of(c, 0))
    if agent.demos is not None:  # ``demo_margin``: DAgger's states and labels, a different count per run
        shape = (SPEC.n_agents, SPEC.obs_dim)
        obs = [g.standard_normal((40 + 7 * k, *shape)).astype(np.float32) for k in range(runs)]
        agent.keep_demonstrations(obs, [g.integers(0, SPEC.max_actions, (len(o), SPEC.n_agents)) for o in obs])
    batch = agent.sample()
    agent.sample = lambda: batch.map(torch.clone)  # type: ignore[method-assign]
    return agent


def adams(lrs: list[float], seed: int = 0) -> tuple[list[torch.Tensor], list[list[torch.Tensor]]]:
    """Stacked parameters ``[R, …]`` and each run's own copy of them."""
    g = torch.Generator().manual_seed(seed)
    stacked = [torch.randn(len(lrs), *s, generator=g) for s in SHAPES]
    return stacked, [[p[k].clone().requires_grad_(True) for p in stacked] for k in range(len(lrs))]


def test_run_adam_is_torch_adam_per_run_and_a_run_not_ok_keeps_its_state() -> None:
    """Runs with their own learning rates step as ``torch.optim.Adam`` of that rate does: measured, the gap after
    60 steps is ≤ 6e-8 (float rounding: the population's foreach arithmetic beside torch's fused kernel, bias
    corrections in float64 as torch takes them); a run not ok — NaN gradients — keeps weights, moments and step
    count exactly, and the others step as if it were not there."""
    lrs = [1e-3, 3e-4, 2e-3]
    stacked, singles = adams(lrs)
    opt = RunAdam(stacked, torch.tensor(lrs))
    theirs = [torch.optim.Adam(p, lr=lr, fused=True) for p, lr in zip(singles, lrs, strict=True)]
    g = torch.Generator().manual_seed(1)
    for i in range(60):
        grads = [torch.randn(len(lrs), *s, generator=g) for s in SHAPES]
        ok = torch.tensor([True, i % 3 != 0, True])  # run 1 skips every third step
        if i % 3 == 0:
            grads[0][1] = math.nan
        kept = [p[1].clone() for p in stacked], [st.clone() for st in opt.state_dict()["state"][0].values()]
        opt.step_runs([gr.clone() for gr in grads], ok)
        for k, (params, adam) in enumerate(zip(singles, theirs, strict=True)):
            if bool(ok[k]):
                for p, gr in zip(params, grads, strict=True):
                    p.grad = gr[k].clone()
                adam.step()
        if i % 3 == 0:  # run 1 as it was, exactly
            assert all(torch.equal(p[1], old) for p, old in zip(stacked, kept[0], strict=True))
            now = opt.state_dict()["state"][0].values()
            assert all(torch.equal(v[1], old[1]) for v, old in zip(now, kept[1], strict=True))
    for k, (params, adam) in enumerate(zip(singles, theirs, strict=True)):
        for p, mine in zip(params, stacked, strict=True):
            torch.testing.assert_close(mine[k], p.detach(), rtol=0, atol=6e-8)
        for i, st in adam.state_dict()["state"].items():
            ours = opt.state_dict()["state"][i]
            assert float(ours["step"][k]) == float(st["step"]) == (60 if k != 1 else 40)
            torch.testing.assert_close(ours["exp_avg"][k], st["exp_avg"], rtol=0, atol=1e-7)
            torch.testing.assert_close(ours["exp_avg_sq"][k], st["exp_avg_sq"], rtol=0, atol=1e-7)


def test_a_single_runs_adam_is_torchs_fused_adam_and_loads_its_checkpoints() -> None:
    """A single run (a run axis of 1) steps with torch's fused kernel (the same arithmetic, its learning rate a
    device tensor) and takes over the state ``torch.optim.Adam(fused=True)`` wrote (every checkpoint before RunAdam),
    given the run axis as ``NetworkAgent.load_member_state`` gives it: steps go on equal. A skipped step
    (``found_inf`` on the device) changes nothing."""
    stacked, (params,) = adams([1e-3])
    ours = [p.clone() for p in stacked]
    theirs = torch.optim.Adam(params, lr=1e-3, fused=True)
    g = torch.Generator().manual_seed(2)

    def grads() -> list[torch.Tensor]:
        return [torch.randn(*s, generator=g) for s in SHAPES]

    for _ in range(5):  # the old checkpoint: five steps of torch's Adam
        for p, gr in zip(params, grads(), strict=True):
            p.grad = gr
        theirs.step()
    for mine, p in zip(ours, params, strict=True):
        mine[0].copy_(p.detach())
    opt = RunAdam(ours, torch.tensor([1e-3]))
    saved = copy.deepcopy(theirs.state_dict())  # as from a file: no tensor shared with theirs
    saved["state"] = {i: {k: v[None] for k, v in st.items()} for i, st in saved["state"].items()}  # run axis
    opt.load_state_dict(saved)
    assert opt.state_dict()["state"][0]["step"] == 5
    before = [p.clone() for p in ours]
    opt.step_runs([torch.full((1, *s), math.nan) for s in SHAPES], torch.tensor([False]))
    assert all(torch.equal(a, b) for a, b in zip(ours, before, strict=True))
    assert opt.state_dict()["state"][0]["step"] == 5
    for _ in range(20):
        gs = grads()
        for p, gr in zip(params, gs, strict=True):
            p.grad = gr.clone()
        theirs.step()
        opt.step_runs([gr[None] for gr in gs], torch.tensor([True]))
    for mine, p in zip(ours, params, strict=True):
        torch.testing.assert_close(mine[0], p.detach(), rtol=1e-6, atol=1e-9)  # lr: float32 here, float64 there


def test_an_update_reads_nothing_back_to_the_host(monkeypatch: pytest.MonkeyPatch) -> None:
    """No ``item``/``float``/``bool``/``numpy``/``tolist`` of a tensor in an update — a single run's or a
    population's, with a non-finite run, annealing, per-run target periods, Polyak targets and a policy average —
    and reading the figures is one host read for many updates."""
    single = filled("idqn", 3, lr_end=1e-4, policy_ema=0.5)
    pop = filled("ma-mesn", SEEDS, gumbel_noise=0.0, target_tau=0.5)
    grid = filled("idqn", SEEDS)
    grid.set_run_configs([config("idqn", False, hidden=(16,), batch_size=8, target_update=c) for c in (1, 2, 3)])
    batch = pop.sample()
    batch.reward[1] = math.nan  # run 1 not finite
    pop.sample = lambda: batch.map(torch.clone)  # type: ignore[method-assign]
    rows = {}
    for agent in (single, pop, grid):
        agent.update()  # the first update makes the optimizer (its zero state), outside the count
        with counting(monkeypatch) as mode:
            figures = [agent.update() for _ in range(6)]
        assert not host_reads(mode.ops), f"{agent.name}: host reads {host_reads(mode.ops)}"
        with counting(monkeypatch) as mode:
            rows[agent] = read_figures(figures)
        assert host_reads(mode.ops) == {"host:numpy": 1}  # six updates' figures, one read
    assert np.isnan(rows[pop][-1][1]["loss"]) and np.isfinite(rows[pop][-1][0]["loss"])
    assert pop.updater.skipped_updates == 7 and grid.updater.skipped_updates == 0


def sampling(name: str, runs: int, teacher: Path | None) -> NetworkAgent:
    """``name`` at its noisy defaults (the DRU's σ, Gumbel messages) with replay rows, sampling as in training."""
    cfg = config(name, False, teacher, hidden=(16,), batch_size=8)
    agent = make_algorithm(name, SPEC, cfg, device="cpu", seed=list(range(runs)))
    g = np.random.default_rng(0)
    for _ in range(2):
        agent.observe(chunk(g, runs))
    return agent


@pytest.mark.parametrize("name", POPULATION_ALGOS)
def test_an_update_dispatches_as_many_ops_for_20_runs_as_for_one(
    name: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Every algorithm's update — the replay's sample, the noise draws (DIAL's DRU, Gumbel messages), loss, clip,
    guard, Adam, figures — is the same ops whatever the population's size: no per-run loop anywhere, so on a GPU
    twenty runs launch what two do, and none reads back to the host. A run of one takes the one-run kernels
    (``addmm``, torch's fused Adam: a single run's numbers, bit for bit), no more ops than those."""
    teacher = save_teacher(tmp_path / "teacher.pt") if name == "codbc" else None
    counts = {}
    for runs in (1, 2, 20):
        agent = sampling(name, runs, teacher)
        agent.update()
        with counting(monkeypatch) as mode:
            agent.update()
        counts[runs] = mode.ops
        assert not host_reads(mode.ops), f"R = {runs}: host reads {host_reads(mode.ops)}"
    assert counts[2] == counts[20]
    assert 50 < sum(counts[1].values()) <= sum(counts[20].values())  # ops were counted


def test_read_figures_fails_a_run_that_stayed_non_finite_naming_its_seed() -> None:
    pop = filled("idqn", SEEDS)
    batch = pop.sample()
    batch.reward[2] = math.inf
    pop.sample = lambda: batch.map(torch.clone)  # type: ignore[method-assign]
    figures = [pop.update() for _ in range(MAX_NONFINITE_IN_A_ROW + 3)]  # nothing read, nothing fails
    read_figures(figures[: MAX_NONFINITE_IN_A_ROW - 1])
    with pytest.raises(FloatingPointError, match=rf"run of seed {SEEDS[2]}\): {MAX_NONFINITE_IN_A_ROW} updates"):
        read_figures(figures)


# --- compile: one captured graph -----------------------------------------------------------------------------------
NOISELESS = {"ma-mesn": {"gumbel_noise": 0.0}, "ma-bon": {"gumbel_noise": 0.0}, "dial": {"dru_sigma": 0.0}}
MARGIN = {"demonstrator": "planner", "demo_margin": 1.0}


@pytest.mark.slow  # Dynamo traces each update: ~4 s apiece on a shared 2-core machine
@pytest.mark.parametrize(
    "name, params",
    [
        ("idqn", {}),
        ("ma-mesn", NOISELESS["ma-mesn"]),
        ("ma-bon", NOISELESS["ma-bon"]),
        ("dial", NOISELESS["dial"]),
        # noise drawn in training (the DRU's, Gumbel messages, a noise control): one draw from the runs' counter
        # streams (algos/streams.py), inside the graph
        ("dial", {}),
        ("ma-mesn", {}),
        ("ma-bon", {"channel_control": "noise"}),
        ("idqn", {"heads": 3, "share_params": True}),  # Bootstrapped DQN: every head's target in the one graph
        ("idqn", {"priority_alpha": 0.6}),  # prioritized replay: importance weights in, |TD errors| out
        ("ma-mesn", {**NOISELESS["ma-mesn"], **MARGIN}),  # DQfD's margin: demonstrations in the batch
    ],
    ids=[
        "idqn",
        "ma-mesn-noiseless",
        "ma-bon-noiseless",
        "dial-noiseless",
        "dial",
        "ma-mesn",
        "ma-bon-noise-control",
        "idqn-heads",
        "idqn-prioritized",
        "ma-mesn-demo-margin",
    ],
)
def test_the_update_from_its_batch_is_one_graph(name: str, params: dict[str, Any]) -> None:
    pop = filled(name, SEEDS, **params)
    pop.updater.optimizer  # noqa: B018  (made before tracing, as update does)
    with torch._dynamo.config.patch(trace_autograd_ops=True):
        explained = torch._dynamo.explain(pop.updater._step)(pop.sample())
    assert (explained.graph_count, explained.graph_break_count) == (1, 0), explained.break_reasons


@pytest.mark.slow  # compiles (Inductor, C++): ~20 s apiece on a 2-core machine
@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
@pytest.mark.parametrize("name, seeds", [("idqn", SEEDS[:2]), ("ma-mesn", 3)], ids=["idqn-population", "ma-mesn"])
def test_a_compiled_update_is_the_eager_update(name: str, seeds: int | list[int], device: str) -> None:
    """``compile``: the same figures and weights as eager updates over 100 updates, to 1e-5 (measured on a CPU:
    ≤ 6e-8; Inductor fuses the same arithmetic in another order), from one compiled graph — on CUDA also one CUDA
    graph, whose figures stay right when read after later replays; a run whose loss is not finite keeps its
    weights there too."""
    torch.set_num_threads(1)
    eager = filled(name, seeds, device, **NOISELESS.get(name, {}))
    compiled = filled(name, seeds, device, compile=True, **NOISELESS.get(name, {}))
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    for _ in range(20):  # figures read in fives, as the trainer reads them in batches
        wants, gots = [eager.update() for _ in range(5)], [compiled.update() for _ in range(5)]
        for want, got in zip(read_figures(wants), read_figures(gots), strict=True):
            for w, g in zip(want, got, strict=True):
                assert w.keys() == g.keys() and all(g[k] == pytest.approx(v, rel=1e-5, abs=1e-6) for k, v in w.items())
    for (n, a), b in zip(eager.online.state_dict().items(), compiled.online.state_dict().values(), strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-5, msg=f"{n}: max gap {(b - a).abs().max():.3g}")
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1  # compiled once, never again
    assert torch._dynamo.utils.counters["inductor"]["cudagraph_skips"] == 0  # on CUDA: replayed as a CUDA graph
    batch = compiled.sample()
    batch.reward[-1] = math.nan  # the last run (a single run: the whole batch)
    compiled.sample = lambda: batch  # type: ignore[method-assign]
    before = run_state(compiled.online, compiled.runs - 1)
    before = {k: v.clone() for k, v in before.items()}
    figures = compiled.update().read()
    assert math.isnan(figures[-1]["loss"])
    after = run_state(compiled.online, compiled.runs - 1)
    assert all(torch.equal(before[k], v) for k, v in after.items())
