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


def test_shuffled_messages_come_from_other_envs_and_modal_is_each_senders_most_common() -> None:
    """The in-distribution controls: shuffled hears another env's real messages of this step (no env its own);
    modal hears each sender's most frequent message so far, the same in every env."""
    import torch

    from convoy.algos.listening import Listening

    true = torch.zeros(6, 2, 1, 3)  # [B, receivers, senders, bits]
    true[:, 0, 0] = torch.tensor(
        [[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1]], dtype=torch.float32
    )
    true[:, 1, 0] = torch.tensor([1.0, 1.0, 1.0])
    shuffled = Listening("shuffled", seed=0).hear(true)
    rows = [tuple(r.tolist()) for r in shuffled[:, 0, 0]]
    assert sorted(rows) == sorted(tuple(r.tolist()) for r in true[:, 0, 0])  # the same messages, reassigned
    assert all((shuffled[b] != true[b]).any() for b in range(6))  # no env hears its own
    modal = Listening("modal", seed=0)
    first = modal.hear(true)
    assert (first[:, 1, 0] == 1).all()  # receiver 1 always heard 111
    again = true.clone()
    again[:, 0, 0] = torch.tensor([0.0, 1.0, 1.0])  # 011 now the most frequent for receiver 0 (1 + 6 times)
    assert (modal.hear(again)[:, 0, 0] == torch.tensor([0.0, 1.0, 1.0])).all()
    fixed = Listening("fixed", seed=0).hear(true)  # the cut channel's constant, whatever was sent
    assert fixed.shape == true.shape and not fixed.any()
