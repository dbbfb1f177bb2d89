"""Algorithm names → classes, imported on first use (one module per algorithm under ``learner/algos``)."""

from __future__ import annotations

import importlib

import torch

from envs.batched import EnvSpec
from learner.algorithm import Algorithm
from protocol.config import AlgoConfig, algo_name

ALGORITHMS: dict[str, str] = {
    "idqn": "learner.algos.idqn:IndependentDQN",
    "dqn-ser": "learner.algos.dqn_ser:DQNSER",
    "dial": "learner.algos.dial:DIAL",
    "ims": "learner.algos.ims:IMS",
    "ma-mesn": "learner.algos.ma_mesn:MAMeSN",
    "ma-bon": "learner.algos.ma_bon:MABoN",
    "ma-mesn-mm": "learner.algos.ma_mesn_mm:MAMeSNMM",
    "ma-bon-mm": "learner.algos.ma_bon_mm:MABoNMM",
    "codbc": "learner.algos.codbc:CoDBC",
}


def algorithm_class(name: str) -> type[Algorithm]:
    module, _, attr = ALGORITHMS[algo_name(name)].partition(":")
    return getattr(importlib.import_module(module), attr)


def make_algorithm(
    name: str, spec: EnvSpec, cfg: AlgoConfig, device: str | torch.device = "auto", seed: int = 0
) -> Algorithm:
    """Build algorithm ``name`` for env ``spec`` with a resolved config (see ``protocol.config.resolve_algo``)."""
    return algorithm_class(name)(spec, cfg, device=device, seed=seed)
