"""The tests' fixed clocks are the reference machine's seconds: a slower or loaded machine gets more."""

import pytest

from tests.pace import MOST, paced, slowness


@pytest.mark.timeout(7)
def test_a_hang_guard_is_scaled_by_the_machines_pace(request: pytest.FixtureRequest) -> None:
    guard = request.node.get_closest_marker("timeout")
    assert guard is not None and 7 <= guard.args[0] <= 7 * MOST


def test_the_default_hang_guard_is_scaled_too(request: pytest.FixtureRequest) -> None:
    guard = request.node.get_closest_marker("timeout")
    assert guard is not None and guard.args[0] >= float(request.config.getoption("timeout"))


def test_a_paced_wait_is_never_shorter_than_the_one_named() -> None:
    assert 1.0 <= slowness() <= MOST and 2.0 <= paced(2.0) <= 2.0 * MOST
