"""The test tiers: ``make test-fast`` runs ``pytest -m "not slow"`` (unit tests of the envs, the wire, the configs and
the algorithms' mechanics: about a minute on 2 cores), ``make test`` (what CI runs) runs every test.

A test is slow when it starts processes or servers, drives a browser, or trains to a learning result: every test of
a module in ``SLOW_MODULES``, and tests marked ``@pytest.mark.slow`` in the other modules.
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
import torch
from torch import Tensor, nn

from convoy.algos.algorithm import Agent
from convoy.envs.batched import EnvSpec
from tests.pace import slowness

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

# One torch intra-op thread in every test process and in every process a test starts (they inherit the variable), as
# the learner and the actors run (``torch_threads=1``): the test workers already fill the cores, and OpenMP threads
# oversubscribing a shared box make small ops several times slower (the decoding probe's fit: 3.6 ×). It also keeps a
# test's float path the same on machines with any number of cores. OMP_NUM_THREADS set by the caller wins.
os.environ.setdefault("OMP_NUM_THREADS", "1")
THREADS = int(os.environ["OMP_NUM_THREADS"])


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow: starts processes, servers or a browser, or trains (not in test-fast)")
    config.addinivalue_line(
        "markers",
        "docs_budget(budget): runs a documented command at the budget the docs show (minutes, said in `budget`); "
        "skipped unless CONVOY_DOCS_BUDGET=1 (make docs-check)",
    )


def pytest_report_header() -> str:
    return f"pace: this machine takes {slowness():.1f} × the reference machine's time now (tests/pace.py)"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow = slowness()  # the hang guards (``timeout`` marks, --timeout) in the reference machine's seconds
    for item in items:
        guard = item.get_closest_marker("timeout")
        seconds = float(guard.args[0]) if guard is not None and guard.args else float(config.getoption("timeout") or 0)
        if seconds > 0:
            item.add_marker(pytest.mark.timeout(seconds * slow), append=False)
        module = getattr(item, "module", None)  # a test function's module (pytest.Item does not declare it)
        if module is not None and module.__name__.rsplit(".", 1)[-1] in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)
        budget = item.get_closest_marker("docs_budget")
        if budget is not None:
            item.add_marker(pytest.mark.slow)
            if os.environ.get("CONVOY_DOCS_BUDGET") != "1":
                reason = f"at the documented budget ({budget.args[0]}): CONVOY_DOCS_BUDGET=1 (make docs-check)"
                item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture(autouse=True)
def _threads() -> Iterator[None]:
    """Each test starts on the session's thread count, whatever a test before it in this worker set (a trainer's
    ``torch_threads``, ``--threads``)."""
    torch.set_num_threads(THREADS)
    yield


def synthetic_spec(n_agents: int = 3, obs_dim: int = 5, n_actions: int = 3) -> EnvSpec:
    """A shape-only env spec, so tests can vary N freely: the algorithms never look past the shapes."""
    return EnvSpec(
        name="synthetic",
        agent_ids=tuple(f"agent_{i}" for i in range(n_agents)),
        obs_dims=(obs_dim,) * n_agents,
        n_actions=(n_actions,) * n_agents,
        max_steps=10,
    )


def grad(module: nn.Module, name: str) -> Tensor:
    """The gradient of ``module``'s parameter ``name`` (dotted, as ``named_parameters`` says), which must have one."""
    g = module.get_parameter(name).grad
    assert g is not None, f"no gradient reached {name}"
    return g


def single_update(algo: Agent) -> dict[str, float]:
    """``algo.update()`` of a single run (a population of one), read: its one dict of figures."""
    (figures,) = algo.update().read()
    return figures


def population_update(algo: Agent) -> list[dict[str, float]]:
    """``algo.update()`` of a population, read: one dict of figures per run."""
    return algo.update().read()
