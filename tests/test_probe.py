"""The decoding probe (``analysis/probe.py``): its target is what only teammates observe, and its classifier finds
information where it is and none where it is not."""

import numpy as np

from convoy.analysis.probe import SECTORS, adversary_sector, heard, probe_accuracy
from convoy.envs.treadmill import TreadmillConfig
from convoy.envs.treadmill.engine import TreadmillEngine


def test_the_target_is_an_adversary_only_a_teammate_observes() -> None:
    cfg = TreadmillConfig(n_agents=2, n_adversaries=1)
    e = TreadmillEngine(cfg, 1)
    e.reset(0)
    # agent 0 faces forward at (50, 50); the adversary sits behind it, in its blind spot; agent 1 ahead, facing back
    e.x[0], e.y[0], e.heading[0] = [50, 70, 40], [50, 50, 50], [0, 4, 0]
    valid, label = adversary_sector(e)
    assert valid[0].tolist() == [True, False]  # agent 1 sees it itself: nothing to tell it
    assert label[0, 0] == 4  # behind agent 0: the −x direction
    e.heading[0, 1] = 0  # agent 1 turns forward: now nobody sees the adversary
    assert not adversary_sector(e)[0].any()


def test_heard_is_every_peers_bits_in_order() -> None:
    bits = np.arange(3 * 2).reshape(1, 3, 2)  # agent i sends [2i, 2i+1]
    assert heard(bits)[0].tolist() == [[2, 3, 4, 5], [0, 1, 4, 5], [0, 1, 2, 3]]


def test_the_probe_finds_what_the_features_carry_and_nothing_else() -> None:
    rng = np.random.default_rng(0)
    labels = rng.integers(0, SECTORS, (40, 16, 3))
    valid = rng.random(labels.shape) < 0.7
    carries = np.eye(SECTORS)[labels]  # the label, one-hot
    acc, majority, samples = probe_accuracy(carries, labels, valid)
    assert acc > 0.95 and samples > 500
    noise = rng.random((*labels.shape, SECTORS))
    acc, majority, _ = probe_accuracy(noise, labels, valid)
    assert acc < majority + 0.06
