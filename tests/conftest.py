"""The test tiers: ``make test-fast`` runs ``pytest -m "not slow"`` (unit tests of the envs, the wire, the configs and
the algorithms' mechanics: about a minute on 2 cores), ``make test`` (what CI runs) runs every test.

A test is slow when it starts processes or servers, drives a browser, or trains to a learning result: every test of
a module in ``SLOW_MODULES``, and tests marked ``@pytest.mark.slow`` in the other modules.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch

from convoy.envs.batched import EnvSpec

SLOW_MODULES = {
    "test_algo_benchmarks",  # runs the benchmark scripts
    "test_api",  # a real convoy serve with real jobs
    "test_api_schema",
    "test_benchmarks",
    "test_compose",
    "test_dashboard",  # headless Chromium
    "test_decentralized",  # trains teachers and students
    "test_eval_cli",
    "test_jobs_cli",
    "test_learning",  # learning results over seeds
    "test_multihost",  # network namespaces
    "test_runtime",  # actor and learner processes over Zenoh
    "test_runtime_benchmark",
    "test_train_cli",
    "test_treadmill_references",  # ≥ 500 episodes per reference policy
}


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow: starts processes, servers or a browser, or trains (not in test-fast)")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Single-threaded torch for a test: tiny batched matmuls are many times faster on one thread than with
    OpenMP threads oversubscribing a shared 2-core box (and the trainer runs with ``torch_threads=1``)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def synthetic_spec(n_agents: int = 3, obs_dim: int = 5, n_actions: int = 3) -> EnvSpec:
    """A shape-only env spec, so tests can vary N freely: the algorithms never look past the shapes."""
    return EnvSpec(
        name="synthetic",
        agent_ids=tuple(f"agent_{i}" for i in range(n_agents)),
        obs_dims=(obs_dim,) * n_agents,
        n_actions=(n_actions,) * n_agents,
        max_steps=10,
    )
