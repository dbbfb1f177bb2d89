"""Algorithm names → classes (``convoy.config.ALGORITHMS``), imported on first use: one module per algorithm."""

from __future__ import annotations

import importlib
from collections.abc import Sequence

import torch

from convoy.algos.algorithm import NetworkAgent
from convoy.config import ALGORITHMS, AlgoConfig, algo_name, resolve_algo
from convoy.envs.batched import EnvSpec


def algorithm_class(name: str) -> type[NetworkAgent]:
    module, _, attr = ALGORITHMS[algo_name(name)].impl.partition(":")
    cls: type[NetworkAgent] = getattr(importlib.import_module(module), attr)  # the table names a NetworkAgent
    return cls


def make_algorithm(
    name: str,
    spec: EnvSpec,
    cfg: AlgoConfig,
    device: str | torch.device = "auto",
    seed: int | Sequence[int] = 0,
    run_configs: Sequence[AlgoConfig] | None = None,
) -> NetworkAgent:
    """Build algorithm ``name`` for env ``spec`` with a resolved config (see ``convoy.config.resolve_algo``); a
    sequence of seeds makes a population, ``run_configs`` (one per seed) its runs' own hyper-parameters."""
    if cfg.match_parameters is not None:
        cfg = widened(name, spec, cfg)
    agent = algorithm_class(name)(spec, cfg, device=device, seed=seed)
    if run_configs is not None:
        agent.set_run_configs(run_configs)
    return agent


def n_parameters(name: str, spec: EnvSpec, cfg: AlgoConfig) -> int:
    """Parameters of one run of algorithm ``name`` on ``spec`` (built on the CPU and dropped)."""
    return algorithm_class(name)(spec, cfg, device="cpu", seed=0).n_parameters()


def widened(name: str, spec: EnvSpec, cfg: AlgoConfig) -> AlgoConfig:
    """``cfg`` with every hidden layer widened by the least common factor that gives ``name`` at least the
    parameters of ``cfg.match_parameters`` with the same settings: a gain over the wider network is not size."""
    other = str(cfg.match_parameters)
    fields = ALGORITHMS[other].config.model_fields
    shared = {k: v for k, v in cfg.model_dump().items() if k in fields and k != "match_parameters"}
    target = n_parameters(other, spec, resolve_algo(other, spec.name, shared))

    def at(factor: float) -> AlgoConfig:
        widths = tuple(max(1, round(h * factor)) for h in cfg.widths)
        return cfg.model_copy(update={"hidden": widths, "match_parameters": None})

    if n_parameters(name, spec, at(1.0)) >= target:
        return at(1.0)
    low, high = 1.0, 2.0
    while n_parameters(name, spec, at(high)) < target:
        low, high = high, high * 2
    while at(low).widths != at(high).widths and high - low > 1e-6:  # the least factor whose widths reach the target
        mid = (low + high) / 2
        low, high = (low, mid) if n_parameters(name, spec, at(mid)) >= target else (mid, high)
    return at(high)
