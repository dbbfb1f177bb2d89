"""The message channel model: drops, bit flips and latency do what they say."""

import numpy as np

from convoy.envs.channel import ChannelConfig, MessageChannel


def messages(b: int = 64, n: int = 3, bits: int = 16, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, (b, n, bits)).astype(np.float32)


def test_perfect_channel_delivers_every_message_to_every_receiver() -> None:
    m = messages()
    got = MessageChannel().transmit(m)
    assert got.delivered.all()
    for r in range(3):
        assert np.array_equal(got.bits[:, r], m)


def test_drop_one_delivers_nothing_but_your_own() -> None:
    got = MessageChannel(ChannelConfig(drop=1.0), seed=0).transmit(messages())
    eye = np.eye(3, dtype=bool)
    assert (got.delivered == eye).all()
    assert (got.bits[:, ~eye] == 0).all()


def test_drop_rate_matches_probability() -> None:
    got = MessageChannel(ChannelConfig(drop=0.3), seed=1).transmit(messages(b=2000))
    off_diag = got.delivered[:, ~np.eye(3, dtype=bool)]
    assert abs(off_diag.mean() - 0.7) < 0.02


def test_flip_one_inverts_other_agents_bits_only() -> None:
    m = messages()
    got = MessageChannel(ChannelConfig(flip=1.0), seed=0).transmit(m)
    assert np.array_equal(got.bits[:, 0, 1], 1 - m[:, 1])
    assert np.array_equal(got.bits[:, 0, 0], m[:, 0])  # an agent hears itself unchanged


def test_flip_rate_matches_probability() -> None:
    m = messages(b=500)
    got = MessageChannel(ChannelConfig(flip=0.1), seed=2).transmit(m)
    heard = got.bits[:, 0, 1]
    assert abs((heard != m[:, 1]).mean() - 0.1) < 0.01


def test_latency_delivers_the_previous_step() -> None:
    ch = MessageChannel(ChannelConfig(latency=1))
    m1, m2 = messages(seed=1), messages(seed=2)
    assert (ch.transmit(m1).bits == 0).all()  # nothing in flight on the first step
    assert np.array_equal(ch.transmit(m2).bits[:, 0, 1], m1[:, 1])
    ch.reset(np.array([0]))
    got = ch.transmit(m1)
    assert (got.bits[0, 0, 1] == 0).all() and np.array_equal(got.bits[1, 0, 1], m2[1, 1])


def test_from_spec_parses_cli_syntax() -> None:
    ch = MessageChannel.from_spec("drop=0.3, flip=0.01,latency=1")
    assert ch.cfg == ChannelConfig(drop=0.3, flip=0.01, latency=1)
