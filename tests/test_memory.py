"""Memory modules (MA-MeSN-MM, MA-BoN-MM), what agents hear at execution (``Listening``), the channel's
``deliver``, evaluation probes and CoDBC (behaviour cloning of a teacher checkpoint).

Each test pins a mechanism the paper's claims rest on, so that it fails if the mechanism breaks rather than only
if a run stops learning: the supervised memory loss must reach the memory module and nothing else (the TD losses
never see it); the acting state is a window of the agent's own observations that is also what replay trains on;
predictions replace messages only when an evaluation asks for them; impaired channels, white noise and CoDBC's
teacher do exactly what their documentation says; and every misuse is a ``ConfigError`` naming the field to fix.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from convoy.actors.stepping import EnvStepper
from convoy.algos.agent import make_agent
from convoy.algos.algorithm import NetworkAgent, Progress
from convoy.algos.checkpoint import load_checkpoint, save_checkpoint
from convoy.algos.codbc import CoDBC
from convoy.algos.listening import HearsMessages, Listening, Source
from convoy.algos.ma_bon import MABoN
from convoy.algos.ma_mesn import MAMeSN
from convoy.algos.memory import HISTORY, MemoryModule
from convoy.algos.registry import make_algorithm
from convoy.analysis.evaluation import evaluate, listening, listening_for
from convoy.config import ALGORITHMS, job_config, resolve_algo
from convoy.envs import EnvSpec, make_batched
from convoy.envs.channel import ChannelConfig, MessageChannel
from convoy.envs.particle.referential import ReferentialBatch
from convoy.services.training import run_inprocess
from convoy.transition import Transition
from convoy.validation import ConfigError
from tests.conftest import single_update, synthetic_spec

MM_ALGOS = ("ma-mesn-mm", "ma-bon-mm")
TINY = {"hidden": (16,), "message_bits": 4, "learning_starts": 16, "batch_size": 16}
TINY_MEMORY = {"memory_window": 3, "memory_hidden": 8}
SMALL_TREADMILL = {"n_agents": 2, "n_adversaries": 1, "length": 30, "width": 12, "max_steps": 50}
GLIMPSE = {"n_targets": 4, "rounds": 2, "listener_glimpse": True}


def build(name: str, spec: EnvSpec | None = None, seed: int = 0, **params: Any) -> NetworkAgent:
    """A tiny CPU algorithm (message and memory sizes only where the algorithm has them)."""
    torch.manual_seed(seed)
    fields = ALGORITHMS[name].config.model_fields
    base = {k: v for k, v in {**TINY, **TINY_MEMORY}.items() if k in fields}  # what this algorithm has
    cfg = resolve_algo(name, "referential", {**base, **params})
    return make_algorithm(name, spec or synthetic_spec(), cfg, device="cpu", seed=seed)


def build_mm(name: str, spec: EnvSpec | None = None, seed: int = 0) -> MemoryModule:
    """``build`` of a memory-module algorithm (MA-MeSN-MM, MA-BoN-MM)."""
    algo = build(name, spec, seed)
    assert isinstance(algo, MemoryModule)
    return algo


def random_batch(algo: NetworkAgent, m: int = 32, seed: int = 0) -> Transition[Tensor]:
    """A replay-like batch with a float16 history window whose valid steps are marked, as ``act`` stores them."""
    g = torch.Generator().manual_seed(seed)
    n, d, a = algo.n_agents, algo.obs_dim, algo.n_act
    batch = Transition(
        obs=torch.randn(1, m, n, d, generator=g),  # one run's: [R = 1, M, …]
        action=torch.randint(0, a, (1, m, n), generator=g),
        reward=torch.randn(1, m, n, generator=g),
        next_obs=torch.randn(1, m, n, d, generator=g),
        terminated=torch.rand(1, m, generator=g) < 0.3,
        truncated=torch.zeros(1, m, dtype=torch.bool),
        episode=torch.zeros(1, m, dtype=torch.int64),
    )
    if isinstance(algo, MemoryModule):
        window = torch.randn(1, m, algo.window, n, d + 1, generator=g)
        window[..., -1] = 1.0
        batch.extras[HISTORY] = window.to(torch.float16)
    return batch


def all_zero(grad: Tensor | None) -> bool:
    return grad is None or not bool(grad.any())


class CallCounter:
    """Counts forward calls of a module through a forward hook."""

    def __init__(self, module: nn.Module) -> None:
        self.calls = 0
        module.register_forward_hook(self._hook)

    def _hook(self, *_: object) -> None:
        self.calls += 1


# --------------------------------------------------------------------------- 1. the memory loss's reach


@pytest.mark.parametrize("name", MM_ALGOS)
def test_memory_loss_reaches_only_the_memory_module(name: str) -> None:
    algo = build_mm(name)
    loss, stats = algo.memory_loss(random_batch(algo))
    assert loss is not None and loss.shape == (1,)  # one run's
    assert {"memory_loss", "memory_bit_acc", "memory_msg_acc"} <= set(stats)
    assert 0.0 <= stats["memory_bit_acc"] <= 1.0 and 0.0 <= stats["memory_msg_acc"] <= stats["memory_bit_acc"]
    loss.sum().backward()
    memory = [p for p, _ in algo.online.named_parameters() if p.startswith("memory.")]
    assert len(memory) == 6  # input, recurrent and head projections, weights and biases
    for pname, p in algo.online.named_parameters():
        if pname.startswith("memory."):
            assert p.grad is not None and bool(p.grad.any()), f"{pname} got no gradient from the memory loss"
        else:
            assert all_zero(p.grad), f"the memory loss reached {pname}"


@pytest.mark.parametrize("name", MM_ALGOS)
def test_td_loss_leaves_the_memory_module_alone(name: str) -> None:
    algo = build(name)
    algo.agent_losses(random_batch(algo)).sum().backward()
    for pname, p in algo.online.named_parameters():
        if pname.startswith("memory."):
            assert all_zero(p.grad), f"the TD loss reached {pname}"
    assert not all_zero(algo.online.get_parameter("policy.layers.0.weight").grad)  # it did reach the policy


@pytest.mark.parametrize("name", MM_ALGOS)
def test_update_trains_memory_and_reports_its_figures(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    algo = build(name)
    batch = random_batch(algo)
    monkeypatch.setattr(algo, "sample", lambda: batch)  # replay draws replaced by one fixed batch
    before = {k: v.clone() for k, v in algo.online["memory"].state_dict().items()}
    stats = single_update(algo)
    assert {"loss", "memory_loss", "memory_bit_acc", "memory_msg_acc"} <= set(stats)
    after = algo.online["memory"].state_dict()
    assert all(not torch.equal(before[k], after[k]) for k in before)


def test_memory_loss_without_history_says_what_is_missing() -> None:
    algo = build_mm("ma-mesn-mm")
    batch = random_batch(algo)
    del batch.extras[HISTORY]
    with pytest.raises(KeyError, match="history"):
        algo.memory_loss(batch)


# --------------------------------------------------------------------------- 2. the history window


def test_push_shifts_in_the_newest_observation_marked_real() -> None:
    algo = build("ma-mesn-mm")
    assert isinstance(algo, MemoryModule)
    b, n, d, window = 4, algo.n_agents, algo.obs_dim, algo.window
    g = torch.Generator().manual_seed(1)
    state = torch.randn(1, b, window, n, d + 1, generator=g)  # one run's
    obs = torch.randn(1, b, n, d, generator=g)
    new = algo.push(state, obs)
    assert new.shape == (1, b, window, n, d + 1)
    fresh = algo.push(None, obs)[0]  # no state yet: zero padding before the first step
    new, state, obs = new[0], state[0], obs[0]
    assert torch.equal(new[:, :-1], state[:, 1:])  # the oldest step is gone, the rest moved up
    assert torch.equal(new[:, -1, :, :d], obs)
    assert bool((new[:, -1, :, d] == 1.0).all())
    assert bool((fresh[:, :-1] == 0).all()) and torch.equal(fresh[:, -1], new[:, -1])


def test_reset_state_zeroes_only_the_finished_envs() -> None:
    algo = build_mm("ma-bon-mm")
    state = torch.randn(1, 4, algo.window, algo.n_agents, algo.obs_dim + 1)  # one run's
    original = state.clone()
    done = np.array([True, False, True, False])
    out = algo.reset_state(state, done)
    assert bool((out[0, torch.as_tensor(done)] == 0).all())
    assert torch.equal(out[0, torch.as_tensor(~done)], original[0, torch.as_tensor(~done)])
    assert torch.equal(state, original)  # the caller's tensor is not modified in place
    assert algo.reset_state(state, np.zeros(4, dtype=bool)) is state


@pytest.mark.parametrize("name", MM_ALGOS)
def test_act_stores_the_window_it_acted_on(name: str) -> None:
    algo = build_mm(name)
    b, n, d = 5, algo.n_agents, algo.obs_dim
    rng = np.random.default_rng(0)
    state = algo.initial_state(b)
    for _ in range(2):
        obs = rng.normal(size=(b, n, d)).astype(np.float32)
        out = algo.act(obs, 0.0, state)
        hist = out.extras[HISTORY]
        assert hist.dtype == np.float16 and hist.shape == (b, algo.window, n, d + 1)
        np.testing.assert_array_equal(hist, out.state[0].to(torch.float16).numpy())  # the state keeps its run axis
        np.testing.assert_array_equal(hist[:, -1, :, :d], obs.astype(np.float16))
        state = out.state


def test_env_stepper_records_history_and_clears_it_between_episodes() -> None:
    env = make_batched("referential", 8, **GLIMPSE)
    algo = build_mm("ma-mesn-mm", env.spec)
    stepper = EnvStepper(env, algo, seed=0)
    for _ in range(3):  # two rounds = one whole episode, then the first step of the next
        stepper.step(0.5)
    chunk = stepper.take_chunk()
    hist, obs = chunk.extras[HISTORY][:, 0], chunk.obs[:, 0]  # [T, R = 1, B, …]: the run's
    d = env.spec.obs_dim
    assert hist.dtype == np.float16 and hist.shape == (3, 8, algo.window, 2, d + 1)
    np.testing.assert_array_equal(hist[:, :, -1, :, :d], obs.astype(np.float16))  # the window ends with obs
    np.testing.assert_array_equal(hist[1, :, -2, :, :d], obs[0].astype(np.float16))  # same episode: remembered
    assert (hist[2, :, :-1] == 0).all()  # a new episode: nothing of the previous one is left
    algo.observe(chunk)  # and the replay can train on it
    _, stats = algo.memory_loss(algo.sample())
    assert np.isfinite(float(stats["memory_loss"]))


# --------------------------------------------------------------------------- 3. predictions only when asked


@pytest.mark.parametrize("name", MM_ALGOS)
def test_predictions_replace_messages_only_when_asked(name: str) -> None:
    algo = build(name, seed=3)
    assert isinstance(algo, MemoryModule)
    g = torch.Generator().manual_seed(2)
    b = 64
    obs = torch.randn(1, b, algo.n_agents, algo.obs_dim, generator=g)  # one run's
    state = algo.push(algo.initial_state(b), torch.randn(1, b, algo.n_agents, algo.obs_dim, generator=g))
    with torch.no_grad():
        window = algo.push(state, obs)
        x, _, heard = algo.speak(algo.online, obs, False)
        predicted = (algo.predict(algo.online, window) > 0).to(heard.dtype)
        q_true = algo.forward(algo.online, obs, False)[0]
        q_pred = algo.listen(algo.online, x, predicted)
        q_zero = algo.listen(algo.online, x, torch.zeros_like(heard))
    # the three are distinguishable, so the equalities below say which one the policy read
    assert not torch.equal(predicted, heard) and not torch.allclose(q_pred, q_true)
    assert not torch.allclose(q_zero, q_true) and not torch.allclose(q_zero, q_pred)
    counter = CallCounter(algo.online["memory"])

    def greedy(how: Listening | None) -> Tensor:
        algo.listening = how
        with torch.no_grad():
            q, _, new_state = algo.greedy_q(obs, state)
        assert torch.equal(new_state, window)
        return q

    torch.testing.assert_close(greedy(None), q_true)
    assert counter.calls == 0  # the memory module is not even run when nobody asks for it
    torch.testing.assert_close(greedy(Listening("predicted")), q_pred)
    assert counter.calls == 1
    lossy = MessageChannel(ChannelConfig(drop=1.0), seed=0)
    torch.testing.assert_close(greedy(Listening("sent", lossy, fill_lost="predicted")), q_pred)
    torch.testing.assert_close(greedy(Listening("sent", lossy, fill_lost="zeros")), q_zero)
    assert counter.calls == 2  # fill_lost="zeros" needs no prediction
    perfect = MessageChannel(ChannelConfig(), seed=0)
    torch.testing.assert_close(greedy(Listening("sent", perfect, fill_lost="predicted")), q_true)


# --------------------------------------------------------------------------- 4. Listening


def true_messages(seed: int = 0, shape: tuple[int, ...] = (64, 3, 2, 16)) -> Tensor:
    return torch.randint(0, 2, shape, generator=torch.Generator().manual_seed(seed)).float()


def test_noise_is_fair_random_bits_unrelated_to_the_messages() -> None:
    true = true_messages()
    how = Listening("noise", seed=0)
    heard = how.hear(true)
    assert heard.shape == true.shape and heard.dtype == true.dtype
    assert set(torch.unique(heard).tolist()) <= {0.0, 1.0}
    assert abs(float(heard.mean()) - 0.5) < 0.03
    assert abs(float((heard == true).float().mean()) - 0.5) < 0.03  # agrees with the truth only by chance
    assert not torch.equal(how.hear(true), heard)  # fresh bits every step
    torch.testing.assert_close(Listening("noise", seed=0).hear(true), heard)  # reproducible per seed
    ones = Listening("noise", seed=1).hear(torch.ones(64, 3, 2, 16))
    assert abs(float(ones.mean()) - 0.5) < 0.03  # does not depend on what was sent


def test_predicted_without_predictions_names_messages() -> None:
    with pytest.raises(ConfigError, match="ma-mesn-mm") as err:
        Listening("predicted").hear(true_messages())
    assert err.value.field == "messages"
    algo = build("ma-mesn")  # a plain algorithm has nothing to predict with
    assert isinstance(algo, HearsMessages)
    algo.listening = Listening("predicted")
    with pytest.raises(ConfigError) as err:
        algo.act(np.zeros((2, algo.n_agents, algo.obs_dim), np.float32), 0.0)
    assert err.value.field == "messages"


@pytest.mark.parametrize("source", ["predicted", "noise"])
def test_a_channel_carries_only_true_messages(source: Source) -> None:
    with pytest.raises(ConfigError, match=source) as err:
        Listening(source, MessageChannel())
    assert err.value.field == "channel"


def test_unknown_source_names_messages() -> None:
    with pytest.raises(ConfigError, match="sent, predicted, noise") as err:
        Listening("shout")  # type: ignore[arg-type]  # an unknown source, on purpose
    assert err.value.field == "messages"


class RecordingListening(Listening):
    """A ``Listening`` that keeps what the receivers heard, call by call (layout ``[B, R, S, bits]``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.heard: list[Tensor] = []

    def hear(self, true: Tensor, predicted: Tensor | None = None) -> Tensor:
        out = super().hear(true, predicted)
        self.heard.append(out.detach().clone())
        return out


@pytest.mark.parametrize(
    "name",
    [
        "ma-mesn",
        "ma-bon",
        "ma-mesn-mm",
        "ma-bon-mm",
    ],
)
def test_latency_channel_forgets_messages_of_finished_episodes(name: str) -> None:
    algo = build(name, seed=1)
    assert isinstance(algo, MAMeSN | MABoN)
    how = RecordingListening("sent", MessageChannel(ChannelConfig(latency=1), seed=0), fill_lost="zeros")
    algo.listening = how
    rng = np.random.default_rng(0)
    b, n, d = 8, algo.n_agents, algo.obs_dim
    obs1 = rng.normal(size=(b, n, d)).astype(np.float32)
    with torch.no_grad():
        layout = (b, n, algo.senders, algo.bits)  # what Listening sees: [B, receivers, senders, bits]
        true1 = algo.speak(algo.online, torch.as_tensor(obs1)[None], False)[2].reshape(layout)
    assert true1.any()  # something is in flight after the first step
    out = algo.act(obs1, 0.0, algo.initial_state(b))
    assert not how.heard[0].any()  # the first step hears nothing yet
    done = np.array([True, False] * (b // 2))
    state = algo.reset_state(out.state, done)
    algo.act(rng.normal(size=(b, n, d)).astype(np.float32), 0.0, state)
    heard = how.heard[1]
    torch.testing.assert_close(heard[torch.as_tensor(~done)], true1[torch.as_tensor(~done)])  # one step late
    assert not heard[torch.as_tensor(done)].any(), "a new episode heard the previous episode's messages"


def test_evaluation_rounds_start_with_nothing_in_flight() -> None:
    env = make_batched("referential", 4, n_targets=4)  # one-step games: with latency=1 no message ever arrives
    algo = build("ma-mesn-mm", env.spec, seed=1)  # a memory module resets its channel between episodes
    sent = algo.act(env.reset(seed=0), 0.0, algo.initial_state(4)).messages
    assert sent is not None and sent.any()
    how = RecordingListening("sent", MessageChannel(ChannelConfig(latency=1), seed=0), fill_lost="zeros")
    with listening(algo, how):
        evaluate(env, algo, 12, seed=0)  # three rounds of four one-step episodes
    assert len(how.heard) == 3
    assert not how.heard[0].any()
    assert not any(h.any() for h in how.heard[1:]), "a round heard the previous round's messages"


# --------------------------------------------------------------------------- 5. MessageChannel.deliver


def test_deliver_drop_one_loses_everything() -> None:
    got = MessageChannel(ChannelConfig(drop=1.0), seed=0).deliver(true_messages().numpy())
    assert got.bits.shape == (64, 3, 2, 16) and got.delivered.shape == (64, 3, 2)
    assert not got.delivered.any() and (got.bits == 0).all()


def test_deliver_perfect_channel_is_the_identity() -> None:
    m = true_messages().numpy()
    got = MessageChannel(ChannelConfig(drop=0.0, flip=0.0), seed=0).deliver(m)
    assert got.delivered.all() and got.bits.dtype == np.float32
    np.testing.assert_array_equal(got.bits, m)


def test_deliver_flip_one_inverts_every_bit() -> None:
    m = true_messages().numpy()
    got = MessageChannel(ChannelConfig(flip=1.0), seed=0).deliver(m)
    assert got.delivered.all()
    np.testing.assert_array_equal(got.bits, 1.0 - m)


def test_deliver_drop_rate_is_per_receiver_and_sender() -> None:
    got = MessageChannel(ChannelConfig(drop=0.3), seed=1).deliver(true_messages(shape=(2000, 2, 1, 4)).numpy())
    assert abs(got.delivered.mean() - 0.7) < 0.02
    assert (got.bits[~got.delivered] == 0).all()


def test_deliver_latency_one_hears_the_previous_call() -> None:
    ch = MessageChannel(ChannelConfig(latency=1), seed=0)
    m1, m2 = true_messages(1).numpy(), true_messages(2).numpy()
    assert (ch.deliver(m1).bits == 0).all()  # nothing in flight yet
    np.testing.assert_array_equal(ch.deliver(m2).bits, m1)
    ch.reset(np.array([0]))  # env 0's episode ended: its in-flight message is forgotten
    got = ch.deliver(m1).bits
    assert (got[0] == 0).all()
    np.testing.assert_array_equal(got[1:], m2[1:])


@pytest.mark.parametrize("shape", [(4, 3, 16), (4, 3, 2, 2, 16), (16,)])
def test_deliver_rejects_the_wrong_layout(shape: tuple[int, ...]) -> None:
    with pytest.raises(ValueError, match="receivers, senders, bits"):
        MessageChannel().deliver(np.zeros(shape, np.float32))


# --------------------------------------------------------------------------- 6. evaluation.listening_for


def test_listening_for_refuses_probes_without_messages() -> None:
    algo = build("idqn")
    with pytest.raises(ConfigError, match="no discrete message channel") as err:
        listening_for(algo, "noise")
    assert err.value.field == "messages"
    with pytest.raises(ConfigError) as err:
        listening_for(algo, "sent", "drop=0.1")
    assert err.value.field == "channel"
    assert listening_for(algo, "sent") is None  # the true messages need nothing


def test_listening_for_predicted_needs_a_memory_module() -> None:
    with pytest.raises(ConfigError, match="train ma-mesn-mm or ma-bon-mm") as err:
        listening_for(build("ma-mesn"), "predicted")
    assert err.value.field == "messages"
    how = listening_for(build("ma-mesn-mm"), "predicted")
    assert how is not None and how.source == "predicted" and how.needs_prediction


@pytest.mark.parametrize(("spec", "needle"), [("drop=2", "drop"), ("bogus=1", "bogus"), ("drop", "key=value")])
def test_listening_for_bad_channel_names_channel(spec: str, needle: str) -> None:
    with pytest.raises(ConfigError, match=needle) as err:
        listening_for(build("ma-mesn"), "sent", spec)
    assert err.value.field == "channel"


def test_listening_for_parses_a_good_channel() -> None:
    how = listening_for(build("ma-bon"), "sent", "drop=0.3,flip=0.01,latency=1", seed=0)
    assert how is not None and how.channel is not None
    assert how.channel.cfg == ChannelConfig(drop=0.3, flip=0.01, latency=1)


# --------------------------------------------------------------------------- 7. memory figures in the run log


def test_training_logs_memory_figures(tmp_path: Path) -> None:
    job = job_config(
        algo="ma-mesn-mm",
        env="referential",
        env_params=GLIMPSE,
        algo_params={"hidden": (16,), "learning_starts": 64, "memory_window": 2, "memory_hidden": 8},
        steps=3000,
        num_envs=32,
        seed=0,
        eval_episodes=0,
        log_every=500,
        device="cpu",
    )
    run_inprocess(job, out_dir=tmp_path, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    updating = [r for r in rows if r["updates"] > 0]
    assert len(updating) >= 5
    keys = ("memory_loss", "memory_bit_acc", "memory_msg_acc")
    for row in updating:
        assert set(keys) <= set(row), row
        assert row["memory_loss"] > 0 and 0.0 <= row["memory_msg_acc"] <= row["memory_bit_acc"] <= 1.0
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert set(keys) <= set(header)


# --------------------------------------------------------------------------- 8. CoDBC


def treadmill_job(algo: str, **algo_params: Any) -> Any:
    return job_config(
        algo=algo, env="treadmill", env_params=SMALL_TREADMILL, algo_params=algo_params, num_envs=32, device="cpu"
    )


def save_teacher(path: Path, algo: str, env_params: dict[str, Any] | None = None, **algo_params: Any) -> Path:
    """A checkpoint of an untrained ``algo`` (random weights) on a small treadmill. Its seed (7) is not the
    students' (0): with the same seed and sizes an untrained IDQN teacher and its student are the same network."""
    params = {"hidden": (32,), **algo_params}
    job = job_config(
        algo=algo, env="treadmill", env_params=env_params or SMALL_TREADMILL, algo_params=params, device="cpu", seed=7
    )
    env = make_batched("treadmill", 2, **job.env_params)
    teacher = make_agent(job, env.spec, device="cpu")
    return save_checkpoint(path, teacher, job, {"env_steps": 0, "episodes": 0, "updates": 0})


def make_student(teacher: Path | str, num_envs: int = 32, **params: Any) -> tuple[CoDBC, Any]:
    env = make_batched("treadmill", num_envs, **SMALL_TREADMILL)
    torch.manual_seed(0)
    cfg = resolve_algo("codbc", "treadmill", {"teacher": str(teacher), "hidden": (32,), **params})
    algo = make_algorithm("codbc", env.spec, cfg, device="cpu", seed=0)
    assert isinstance(algo, CoDBC)
    algo.progress = Progress(env_steps=0, episodes=0, total_steps=10_000, training=True)  # training has just begun
    return algo, env


def test_codbc_needs_a_teacher() -> None:
    with pytest.raises(ConfigError, match="teacher=PATH") as err:
        resolve_algo("codbc", "treadmill", {})
    assert err.value.field == "teacher"
    with pytest.raises(ConfigError) as err:
        job_config(algo="codbc", env="treadmill")
    assert err.value.field == "teacher"


def test_codbc_missing_teacher_file_fails_on_first_act(tmp_path: Path) -> None:
    student, env = make_student(tmp_path / "nowhere.pt")  # building does not touch the teacher
    with pytest.raises(ConfigError, match="no such file") as err:
        student.act(env.reset(seed=0), 0.0)
    assert err.value.field == "teacher"


def test_codbc_refuses_a_teacher_of_another_env_shape(tmp_path: Path) -> None:
    other = {**SMALL_TREADMILL, "n_agents": 3}
    path = save_teacher(tmp_path / "teacher.pt", "idqn", env_params=other)
    student, env = make_student(path)
    with pytest.raises(ConfigError) as err:
        student.act(env.reset(seed=0), 0.0)
    assert err.value.field == "teacher"
    msg = str(err.value)
    teacher_spec = make_batched("treadmill", 1, **other).spec
    assert repr(teacher_spec) in msg and repr(env.spec) in msg and "same env parameters" in msg


def test_codbc_refuses_a_dial_teacher(tmp_path: Path) -> None:
    path = save_teacher(tmp_path / "dial.pt", "dial", hidden=(16,), message_bits=4)
    student, env = make_student(path)
    with pytest.raises(ConfigError, match="dial") as err:
        student.act(env.reset(seed=0), 0.0)
    assert err.value.field == "teacher"


def test_codbc_clones_its_teacher(tmp_path: Path) -> None:
    path = save_teacher(tmp_path / "teacher.pt", "idqn")
    student, env = make_student(path, lr=3e-3, batch_size=128, learning_starts=256)
    stepper = EnvStepper(env, student, seed=0)
    for _ in range(100):  # 3200 transitions, every env driven by the teacher (progress 0), some exploration
        stepper.step(0.2)
    student.observe(stepper.take_chunk())
    assert student.can_update()
    first = single_update(student)
    assert first["teacher_agreement"] < 0.4, first  # an untrained student agrees only by chance (1/9 actions)
    stats = [single_update(student) for _ in range(300)]
    late = float(np.mean([s["teacher_agreement"] for s in stats[-20:]]))
    assert late > 0.8, late
    # the greedy student now acts as the teacher on fresh states, from its own observations alone
    student.progress = Progress(env_steps=10, episodes=0, total_steps=10)  # past the horizon: the student drives
    obs = env.reset(seed=99)
    agree = (student.act(obs, 0.0).actions == student.teacher_actions(torch.as_tensor(obs)).numpy()).mean()
    assert agree > 0.7, agree


def test_codbc_teacher_share_decays_with_epsilon(tmp_path: Path) -> None:
    student, env = make_student(tmp_path / "never-loaded.pt", teacher_fraction=0.6)
    horizon = int(student.cfg.eps_decay_fraction * 10_000)
    student.progress = Progress(env_steps=0, episodes=0, total_steps=10_000, training=True)
    assert student.teacher_share() == pytest.approx(0.6)
    student.progress = Progress(env_steps=horizon // 2, episodes=0, total_steps=10_000, training=True)
    assert student.teacher_share() == pytest.approx(0.3)
    for steps in (horizon, 10_000):  # the treadmill's ε (and so the teacher's share) decays over the whole run
        student.progress = Progress(env_steps=steps, episodes=0, total_steps=10_000, training=True)
        assert student.teacher_share() == 0.0
    out = student.act(env.reset(seed=0), 0.0)  # with no teacher share the (missing) teacher is never loaded
    assert out.actions.shape == (32, 2)


def test_a_loaded_codbc_checkpoint_acts_as_its_student(tmp_path: Path) -> None:
    teacher = save_teacher(tmp_path / "teacher.pt", "idqn")
    student, env = make_student(teacher)
    job = job_config(
        algo="codbc",
        env="treadmill",
        env_params=SMALL_TREADMILL,
        algo_params={"teacher": str(teacher), "hidden": (32,)},
        device="cpu",
    )
    ckpt = save_checkpoint(tmp_path / "student.pt", student, job, {"env_steps": 10_000, "episodes": 0, "updates": 0})
    teacher.unlink()  # "evaluating a CoDBC checkpoint needs only the student" (algos/codbc.py)
    loaded, _, _ = load_checkpoint(ckpt, device="cpu")
    assert isinstance(loaded, CoDBC)
    obs = env.reset(seed=1)
    greedy = loaded.logits(torch.as_tensor(obs)[None]).argmax(dim=-1)[0].numpy()
    np.testing.assert_array_equal(loaded.act(obs, 0.0).actions, greedy)


# --------------------------------------------------------------------------- 9. the listener's glimpse


def test_listener_glimpse_needs_two_rounds() -> None:
    with pytest.raises(ConfigError, match="rounds") as err:
        make_batched("referential", 4, listener_glimpse=True)
    assert err.value.field == "listener_glimpse"
    with pytest.raises(ConfigError) as err:
        job_config(algo="ma-mesn-mm", env="referential", env_params={"listener_glimpse": True, "rounds": 1})
    assert err.value.field == "listener_glimpse"


def test_glimpse_shows_the_target_on_the_first_round_only() -> None:
    k, b = 4, 16
    env = make_batched("referential", b, n_targets=k, rounds=3, listener_glimpse=True)
    assert isinstance(env, ReferentialBatch)
    eye = np.eye(k, dtype=np.float32)
    obs = env.reset(seed=0)
    targets = env.targets
    np.testing.assert_array_equal(obs[:, 0], eye[targets])
    np.testing.assert_array_equal(obs[:, 1], eye[targets])  # round 0: the listener glimpses the target
    acts = np.zeros((b, 2), dtype=np.int64)
    res = env.step(acts)
    np.testing.assert_array_equal(res.final_obs[:, 1], eye[targets])  # the observation it acted on, unchanged
    for _ in range(2):  # rounds 1 and 2: the listener sees nothing, the speaker still sees the target
        assert (res.obs[:, 1] == 0).all() and not res.terminated.any()
        np.testing.assert_array_equal(res.obs[:, 0], eye[targets])
        res = env.step(acts)  # the scored last round: new targets, a new glimpse
    assert res.terminated.all()
    np.testing.assert_array_equal(res.obs[:, 1], eye[env.targets])
    plain = make_batched("referential", b, n_targets=k, rounds=3)
    assert (plain.reset(seed=0)[:, 1] == 0).all()


def test_shared_fused_lstm_matches_the_grouped_cell() -> None:
    """One group runs torch's fused LSTM, several groups a stepped cell: the same maths, gate for gate."""
    from convoy.algos.memory import GroupLSTM

    torch.manual_seed(0)
    fused, stepped = GroupLSTM(1, 5, 7, 3), GroupLSTM(2, 5, 7, 3)
    with torch.no_grad():
        for g in range(2):  # both groups of the stepped cell get the fused LSTM's weights
            stepped.inp.weight[g] = fused.lstm.get_parameter("weight_ih_l0").T
            stepped.inp.bias[g] = fused.lstm.get_parameter("bias_ih_l0")
            stepped.rec.weight[g] = fused.lstm.get_parameter("weight_hh_l0").T
            stepped.rec.bias[g] = fused.lstm.get_parameter("bias_hh_l0")
            stepped.head.weight[g] = fused.head.weight[0]
            stepped.head.bias[g] = fused.head.bias[0]
    seq = torch.randn(4, 6, 2, 5)  # [M, L, N, in]
    torch.testing.assert_close(fused(seq), stepped(seq))
    assert fused.lstm.get_parameter("bias_ih_l0")[7:14].eq(1.0).all()  # forget gate opened at init


def test_curve_points_measure_the_student_alone(tmp_path: Path) -> None:
    """Mid-run, a learning-curve evaluation plays the student only: the teacher (here a file that does not exist,
    so driving it would fail) never takes a curve episode, though training still hands it 60 % of the envs."""
    from types import SimpleNamespace

    from convoy.learner.runlog import Evaluator

    student, _ = make_student(tmp_path / "never-loaded.pt", teacher_fraction=0.6)
    job = SimpleNamespace(
        eval_episodes=8, eval_every=1_000, seed=0, env="treadmill", env_params=SMALL_TREADMILL, eval_messages="sent"
    )
    evaluator = Evaluator(job, lambda n: make_batched("treadmill", n, **SMALL_TREADMILL))
    try:
        point = evaluator.point(student, 1_000)
    finally:
        evaluator.close()
    assert point["eval_ci95"] >= 0 and student.progress.training and student.teacher_share() > 0
