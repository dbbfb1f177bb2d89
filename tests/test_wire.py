"""The wire schema, the receiving inbox and the key expressions (``protocol.wire``, ``protocol.inbox``,
``protocol.keys``): round trips of every kind (hypothesis), validation on both sides, 10,000 garbage payloads into
one inbox, inbox queue semantics, and key shapes."""

from __future__ import annotations

import collections
import math
import threading
import time
from types import SimpleNamespace
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from convoy.protocol import inbox as inbox_mod
from convoy.protocol import keys, wire
from convoy.protocol.inbox import Inbox
from convoy.protocol.wire import WireError
from convoy.transition import from_columns, record

FAST = settings(
    max_examples=60,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
KINDS = ("chunk", "weights", "budget", "metrics", "command")
DTYPE_LIST = sorted(wire.DTYPES)
INTS = st.integers(-(2**63), 2**64 - 1)  # every int msgpack packs
FLOATS = st.floats(allow_nan=True, allow_infinity=True)
EXTRA_FIELDS = ("logp", "hidden", "msg", "mask")


# --------------------------------------------------------------------------------------------------- helpers
def assert_same(got: Any, exp: Any, path: str = "body") -> None:
    """``got`` (decoded) equals ``exp`` (sent): arrays by dtype, shape and bytes; floats bit-for-bit incl. nan and
    -0.0; tuples come back as lists."""
    if isinstance(exp, np.ndarray):
        assert isinstance(got, np.ndarray), path
        assert got.dtype == exp.dtype, (path, got.dtype, exp.dtype)
        assert got.shape == exp.shape, (path, got.shape, exp.shape)
        assert got.tobytes() == exp.tobytes(), path
        assert np.array_equal(got, exp, equal_nan=exp.dtype.kind == "f"), path
        assert not got.flags.writeable, f"{path}: decoded arrays are read-only views on the payload"
    elif isinstance(exp, dict):
        assert isinstance(got, dict), path
        assert list(got) == list(exp), path
        for k in exp:
            assert_same(got[k], exp[k], f"{path}[{k!r}]")
    elif isinstance(exp, list | tuple):
        assert isinstance(got, list), path
        assert len(got) == len(exp), path
        for i, (g, e) in enumerate(zip(got, exp, strict=True)):
            assert_same(g, e, f"{path}[{i}]")
    elif isinstance(exp, float):
        assert type(got) is float, (path, got)
        if math.isnan(exp):
            assert math.isnan(got), path
        else:
            assert got == exp and math.copysign(1.0, got) == math.copysign(1.0, exp), (path, got, exp)
    else:
        assert type(got) is type(exp), (path, type(got), type(exp))
        assert got == exp, (path, got, exp)


def make_chunk(t: int = 2, b: int = 3, obs_dim: int = 4, seed: int = 0, **extra: np.ndarray) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    arrays: dict[str, np.ndarray] = {
        "obs": rng.standard_normal((t, b, obs_dim)).astype(np.float32),
        "action": rng.integers(0, 5, (t, b)).astype(np.int64),
        "reward": rng.standard_normal((t, b)).astype(np.float32),
        "next_obs": rng.standard_normal((t, b, obs_dim)).astype(np.float32),
        "terminated": rng.random((t, b)) < 0.1,
        "truncated": np.zeros((t, b), dtype=bool),
        "episode": np.arange(t * b, dtype=np.int32).reshape(t, b),
        **extra,
    }
    return wire.chunk_body(
        from_columns(arrays), actor="actor-0", policy_version=7, env_steps=t * b, returns=[1.5, -2.0]
    )


def ext(arr_or_dtype: Any, shape: Any = None, raw: Any = None) -> msgpack.ExtType:
    """An array extension as a sender would write it, or a hand-made (possibly broken) one."""
    if isinstance(arr_or_dtype, np.ndarray):
        a = np.ascontiguousarray(arr_or_dtype)
        return msgpack.ExtType(wire.ARRAY_EXT, msgpack.packb([a.dtype.str, list(a.shape), a.tobytes()]))
    return msgpack.ExtType(wire.ARRAY_EXT, msgpack.packb([arr_or_dtype, shape, raw]))


def raw_chunk_body(t: int = 2, b: int = 3, /, **arrays: Any) -> dict[str, Any]:
    """A chunk body with the arrays as extensions, so that invalid ones can be written (``encode`` refuses)."""
    body = make_chunk(t, b)
    body["arrays"] = {k: ext(v) for k, v in body["arrays"].items()}
    for k, v in arrays.items():
        if v is None:
            del body["arrays"][k]
        else:
            body["arrays"][k] = v
    return body


def envelope(body: Any = None, kind: Any = "chunk", **fields: Any) -> dict[str, Any]:
    env = {"v": wire.VERSION, "kind": kind, "sender": "s", "seq": 0, "t": 0.0, "body": body}
    env.update(fields)
    return env


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


# ------------------------------------------------------------------------------------------------ strategies
@st.composite
def arrays(draw: st.DrawFn, lead: tuple[int, ...] = (), max_dims: int = wire.MAX_DIMS) -> np.ndarray:
    """An array of any wire dtype: rank len(lead)..max_dims (0-d included), zero-size sides included, ≤ 256 items."""
    dtype = np.dtype(draw(st.sampled_from(DTYPE_LIST)))
    shape = list(lead)
    for _ in range(draw(st.integers(0, max_dims - len(lead)))):
        side = draw(st.integers(0, 3))
        shape.append(1 if math.prod(shape) * side > 256 else side)
    return draw(hnp.arrays(dtype, tuple(shape)))


@st.composite
def chunk_bodies(draw: st.DrawFn) -> dict[str, Any]:
    t, b = draw(st.integers(0, 4)), draw(st.integers(0, 4))
    names = list(wire.CHUNK_FIELDS) + draw(st.lists(st.sampled_from(EXTRA_FIELDS), unique=True, max_size=3))
    arrs = {n: draw(arrays(lead=(t, b))) for n in names}
    actor, version, steps = draw(st.text(max_size=20)), draw(INTS), draw(INTS)
    if draw(st.booleans()):
        return wire.chunk_body(from_columns(arrs), actor, version, steps, draw(st.lists(FLOATS, max_size=5)))
    returns = draw(st.lists(st.one_of(INTS, FLOATS), max_size=5))
    return {"arrays": arrs, "actor": actor, "policy_version": version, "env_steps": steps, "returns": returns}


@st.composite
def weights_bodies(draw: st.DrawFn) -> dict[str, Any]:
    state = draw(st.dictionaries(st.text(max_size=12), arrays(), max_size=6))
    return wire.weights_body(draw(INTS), draw(st.text(max_size=10)), state)


budget_bodies = st.fixed_dictionaries({"allowed_steps": INTS, "ingested_steps": INTS, "version": INTS})
metrics_bodies = st.fixed_dictionaries(
    {
        "role": st.text(max_size=10),
        "id": st.text(max_size=10),
        "values": st.dictionaries(st.text(max_size=12), st.one_of(INTS, FLOATS), max_size=8),
    }
)
json_like = st.recursive(
    st.none() | st.booleans() | INTS | FLOATS | st.text(max_size=10) | st.binary(max_size=10) | arrays(max_dims=3),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=20,
)
command_bodies = st.fixed_dictionaries(
    {"op": st.text(max_size=10), "args": st.dictionaries(st.text(max_size=8), json_like, max_size=5)}
)
BODIES = {
    "chunk": chunk_bodies(),
    "weights": weights_bodies(),
    "budget": budget_bodies,
    "metrics": metrics_bodies,
    "command": command_bodies,
}


# ------------------------------------------------------------------------------------------------ round trip
def test_every_kind_has_a_strategy() -> None:
    assert set(BODIES) == set(KINDS)
    for kind in KINDS:  # each is a known kind: an empty body fails its own schema, not "unknown-kind"
        with pytest.raises(WireError) as info:
            wire.validate(kind, {})
        assert info.value.reason == f"bad-{kind}"


@pytest.mark.parametrize("kind", KINDS)
@FAST
@given(data=st.data())
def test_round_trip_every_kind(kind: str, data: st.DataObject) -> None:
    body = data.draw(BODIES[kind], label="body")
    sender, seq = data.draw(st.text(max_size=16), label="sender"), data.draw(INTS, label="seq")
    before = time.time()
    payload = wire.encode(kind, body, sender, seq)
    assert isinstance(payload, bytes)
    msg = wire.decode(payload)
    assert (msg.kind, msg.sender, msg.seq) == (kind, sender, seq)
    assert before - 1 <= msg.t <= time.time() + 1
    assert_same(msg.body, body)
    for view in (bytearray(payload), memoryview(payload)):
        assert_same(wire.decode(view).body, body)


@pytest.mark.parametrize("dtype", DTYPE_LIST)
def test_every_dtype_at_every_rank(dtype: str) -> None:
    """Deterministic companion of the hypothesis test: ranks 0..MAX_DIMS, zero-size and non-empty."""
    state = {}
    for ndim in range(wire.MAX_DIMS + 1):
        shape = tuple(2 if i % 2 else 1 for i in range(ndim))
        state[f"full{ndim}"] = (np.arange(math.prod(shape)) % 3).astype(dtype).reshape(shape)
        if ndim:
            state[f"empty{ndim}"] = np.zeros((*shape[:-1], 0), dtype=dtype)
    body = wire.weights_body(1, "x", state)
    assert_same(wire.decode(wire.encode("weights", body, "s")).body, body)
    assert wire.decode(wire.encode("weights", body, "s")).body["state"]["full0"].shape == ()


def test_special_float_values_round_trip() -> None:
    specials = np.array([np.nan, np.inf, -np.inf, -0.0, 0.0, 1e-45, np.finfo(np.float32).max], dtype=np.float32)
    with np.errstate(over="ignore"):  # float32's max is inf in float16
        half = specials.astype(np.float16)
    body = wire.weights_body(3, "x", {"f4": specials, "f2": half, "f8": specials.astype("f8")})
    assert_same(wire.decode(wire.encode("weights", body, "s")).body, body)
    values = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf, "neg0": -0.0, "big": 2**64 - 1, "small": -(2**63)}
    body = {"role": "learner", "id": "l0", "values": values}
    assert_same(wire.decode(wire.encode("metrics", body, "s")).body, body)


@pytest.mark.parametrize(
    "make",
    [
        lambda a: a.T,
        lambda a: a[::2],
        lambda a: a[::-1, ::-1],
        lambda a: np.asfortranarray(a),
        lambda a: a[:, 1:3],
    ],
    ids=["transposed", "strided", "reversed", "fortran", "sliced"],
)
def test_non_contiguous_arrays_round_trip(make: Any) -> None:
    a = make(np.arange(24, dtype=np.float64).reshape(4, 6))
    got = wire.decode(wire.encode("weights", wire.weights_body(1, "x", {"a": a}), "s")).body["state"]["a"]
    assert got.shape == a.shape and np.array_equal(got, a)


def test_tuples_and_numpy_scalars_in_command_args() -> None:
    args = {"pair": (1, 2), "f": np.float32(0.5), "i": np.int64(-3), "b": np.bool_(True), "nested": {"x": [(3,)]}}
    got = wire.decode(wire.encode("command", {"op": "scale", "args": args}, "api")).body["args"]
    assert got == {"pair": [1, 2], "f": 0.5, "i": -3, "b": True, "nested": {"x": [[3]]}}
    assert type(got["i"]) is int and type(got["b"]) is bool


def test_a_typed_transition_round_trips_through_the_wire() -> None:
    """The acting loop's ``Transition`` is a map of names only inside a chunk's body: it decodes to the same fields,
    attribute by attribute, its extras kept by name."""
    g = np.random.default_rng(0)
    t, b, n, d = 3, 2, 2, 4
    step = record(g.normal(size=(t, b, n, d)), g.integers(0, 5, (t, b, n)), g.normal(size=(t, b, n)),
                  g.normal(size=(t, b, n, d)), g.random((t, b)) < 0.5, g.random((t, b)) < 0.5,
                  g.integers(0, 9, (t, b)), {"mu": g.random((t, b, n)).astype(np.float32)})  # fmt: skip
    sent = wire.encode("chunk", wire.chunk_body(step, "a0", 0, t * b, []), "a0")
    got = wire.chunk_transitions(wire.decode(sent).body)
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "episode"):
        mine, theirs = getattr(step, name), getattr(got, name)
        assert theirs.dtype == mine.dtype and theirs.shape == mine.shape and np.array_equal(theirs, mine), name
    assert set(got.extras) == {"mu"} and np.array_equal(got.extras["mu"], step.extras["mu"])


def test_typed_constructors() -> None:
    chunk = wire.chunk_transitions(make_chunk())
    body = wire.chunk_body(chunk, "a", np.int64(3), np.int32(12), [np.float32(1.5), 2])
    assert body["policy_version"] == 3 and type(body["policy_version"]) is int
    assert type(body["env_steps"]) is int and body["returns"] == [1.5, 2.0]
    assert all(type(r) is float for r in body["returns"])
    wire.validate("chunk", body)
    assert "return_runs" not in body  # a single run's chunk
    pop = wire.chunk_body(chunk, "a", 3, 12, [1.5, 2.0], [np.int64(1), 0])
    assert pop["return_runs"] == [1, 0] and all(type(r) is int for r in pop["return_runs"])
    wire.validate("chunk", pop)
    w = wire.weights_body(np.int64(5), "dqn", {"w": np.ones(2, np.float32)})
    assert type(w["version"]) is int
    wire.validate("weights", w)
    values = {"f": 1.5, "i": 2, "f32": np.float32(0.25), "i64": np.int64(3), "s": "x", "none": None, "b": True}
    m = wire.metrics_body("actor", "a0", values)
    assert m == {"role": "actor", "id": "a0", "values": {"f": 1.5, "i": 2.0, "f32": 0.25, "i64": 3.0}}
    assert all(type(v) is float for v in m["values"].values())
    wire.validate("metrics", m)


# ------------------------------------------------------------------------------------------ encode validates
def _drop(body: dict[str, Any], *names: str) -> dict[str, Any]:
    return {k: v for k, v in body.items() if k not in names}


def _chunk_with(**arrays: Any) -> dict[str, Any]:
    body = make_chunk()
    body["arrays"] = {**body["arrays"], **arrays}
    for k in [k for k, v in body["arrays"].items() if v is None]:
        del body["arrays"][k]
    return body


INVALID_BODIES = [
    *[pytest.param("chunk", _chunk_with(**{f: None}), "bad-chunk", id=f"chunk-no-{f}") for f in wire.CHUNK_FIELDS],
    *[
        pytest.param("chunk", _drop(make_chunk(), f), "bad-chunk", id=f"chunk-no-{f}")
        for f in ("arrays", "actor", "policy_version", "env_steps", "returns")
    ],
    pytest.param("chunk", _chunk_with(reward=np.zeros((2, 4), np.float32)), "bad-chunk", id="chunk-lead-B"),
    pytest.param("chunk", _chunk_with(action=np.zeros((3, 3), np.int64)), "bad-chunk", id="chunk-lead-T"),
    pytest.param("chunk", _chunk_with(logp=np.zeros((2,), np.float32)), "bad-chunk", id="chunk-extra-1d"),
    pytest.param("chunk", _chunk_with(obs=np.zeros((2,), np.float32)), "bad-chunk", id="chunk-obs-1d"),
    pytest.param("chunk", _chunk_with(obs=[[0.0]]), "bad-chunk", id="chunk-list-array"),
    pytest.param("chunk", {**make_chunk(), "arrays": {1: np.zeros((2, 3))}}, "bad-chunk", id="chunk-int-name"),
    pytest.param("chunk", {**make_chunk(), "policy_version": 1.0}, "bad-chunk", id="chunk-float-version"),
    pytest.param("chunk", {**make_chunk(), "policy_version": True}, "bad-chunk", id="chunk-bool-version"),
    pytest.param("chunk", {**make_chunk(), "env_steps": np.int64(3)}, "bad-chunk", id="chunk-np-steps"),
    pytest.param("chunk", {**make_chunk(), "actor": 3}, "bad-chunk", id="chunk-int-actor"),
    pytest.param("chunk", {**make_chunk(), "returns": (1.0,)}, "bad-chunk", id="chunk-tuple-returns"),
    pytest.param("chunk", {**make_chunk(), "returns": [1.0, "x"]}, "bad-chunk", id="chunk-str-return"),
    pytest.param("chunk", {**make_chunk(), "returns": [True]}, "bad-chunk", id="chunk-bool-return"),
    pytest.param("chunk", {**make_chunk(), "returns": [1.0], "return_runs": []}, "bad-chunk", id="chunk-runs-len"),
    pytest.param("chunk", {**make_chunk(), "returns": [1.0], "return_runs": [0.0]}, "bad-chunk", id="chunk-runs-f"),
    pytest.param("chunk", {**make_chunk(), "return_runs": {}}, "bad-chunk", id="chunk-runs-map"),
    pytest.param("weights", {"version": 1, "algo": "x"}, "bad-weights", id="weights-no-state"),
    pytest.param("weights", {"version": 1, "algo": "x", "state": {"w": [1.0]}}, "bad-weights", id="weights-list"),
    pytest.param("weights", {"version": True, "algo": "x", "state": {}}, "bad-weights", id="weights-bool-version"),
    pytest.param("weights", {"version": 1, "algo": None, "state": {}}, "bad-weights", id="weights-no-algo"),
    pytest.param("budget", {"allowed_steps": 1, "ingested_steps": 0}, "bad-budget", id="budget-no-version"),
    pytest.param("budget", {"allowed_steps": 1.5, "ingested_steps": 0, "version": 0}, "bad-budget", id="budget-f"),
    pytest.param("metrics", {"role": "a", "id": "b", "values": {"x": "1"}}, "bad-metrics", id="metrics-str"),
    pytest.param("metrics", {"role": "a", "id": "b", "values": {"x": True}}, "bad-metrics", id="metrics-bool"),
    pytest.param("metrics", {"role": "a", "id": "b", "values": {"x": [1]}}, "bad-metrics", id="metrics-list"),
    pytest.param("metrics", {"role": "a", "id": "b", "values": {1: 1.0}}, "bad-metrics", id="metrics-int-key"),
    pytest.param("metrics", {"role": "a", "values": {}}, "bad-metrics", id="metrics-no-id"),
    pytest.param("command", {"op": "stop"}, "bad-command", id="command-no-args"),
    pytest.param("command", {"op": "stop", "args": []}, "bad-command", id="command-list-args"),
    pytest.param("command", {"op": 1, "args": {}}, "bad-command", id="command-int-op"),
    pytest.param("command", {"op": "x", "args": {1: 2}}, "bad-command", id="command-int-key"),
    pytest.param("command", {"op": "x", "args": {"a": [{"b": {(1, 2): 0}}]}}, "bad-command", id="command-deep-key"),
    pytest.param("chunkz", {}, "unknown-kind", id="unknown-kind"),
    pytest.param("", {}, "unknown-kind", id="empty-kind"),
    pytest.param(None, {}, "unknown-kind", id="none-kind"),
    pytest.param("chunk", None, "bad-envelope", id="body-none"),
    pytest.param("budget", [1, 2, 3], "bad-envelope", id="body-list"),
]


@pytest.mark.parametrize(("kind", "body", "reason"), INVALID_BODIES)
def test_encode_refuses_invalid_bodies(kind: Any, body: Any, reason: str) -> None:
    with pytest.raises(WireError) as info:
        wire.encode(kind, body, "s")
    assert info.value.reason == reason
    assert str(info.value).startswith(reason)
    assert isinstance(info.value, ValueError)


def test_encode_refuses_a_non_str_sender() -> None:
    with pytest.raises(WireError) as info:
        wire.encode("budget", {"allowed_steps": 1, "ingested_steps": 0, "version": 0}, 5)  # type: ignore[arg-type]  # a bad sender, on purpose
    assert info.value.reason == "bad-envelope"


@pytest.mark.parametrize(
    ("value", "match"),
    [
        (np.array([object(), 1], dtype=object), "dtype object"),
        (np.zeros(3, dtype=">i4"), "dtype >i4"),
        (np.zeros(3, dtype=np.complex64), "dtype complex64"),
        (np.zeros(3, dtype="datetime64[s]"), "dtype datetime64"),
        (np.zeros(3, dtype="U3"), "dtype <U3"),
        (np.zeros((1,) * (wire.MAX_DIMS + 1), np.float32), "9 dims"),
    ],
    ids=["object", "big-endian", "complex", "datetime", "unicode", "too-many-dims"],
)
def test_encode_refuses_unsendable_arrays_with_a_clear_type_error(value: np.ndarray, match: str) -> None:
    """Arrays pass the schema (they are arrays) but not the encoder: TypeError naming the problem."""
    for kind, body in (
        ("weights", wire.weights_body(1, "x", {"w": value})),
        ("command", {"op": "x", "args": {"a": value}}),
    ):
        with pytest.raises(TypeError, match=match):
            wire.encode(kind, body, "s")


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ({"op": "x", "args": {"s": {1, 2}}}, "cannot send set"),
        ({"op": "x", "args": {"o": object()}}, "cannot send object"),
        ({"op": "x", "args": {"big": 2**64}}, "64-bit range"),
        ({"op": "x", "args": {"small": -(2**63) - 1}}, "64-bit range"),
    ],
    ids=["set", "object", "int-too-big", "int-too-small"],
)
def test_encode_refuses_unsendable_values(body: dict[str, Any], match: str) -> None:
    with pytest.raises(TypeError, match=match):
        wire.encode("command", body, "s")


def test_encode_refuses_out_of_range_ints_in_validated_fields() -> None:
    with pytest.raises(TypeError, match="64-bit range"):
        wire.encode("budget", {"allowed_steps": 2**64, "ingested_steps": 0, "version": 0}, "s")
    with pytest.raises(TypeError, match="64-bit range"):
        wire.encode("budget", {"allowed_steps": 1, "ingested_steps": 0, "version": 0}, "s", seq=2**64)


# --------------------------------------------------------------------------------------------- decode refuses
def _at_obs(bad: Any) -> bytes:
    return pack(envelope(raw_chunk_body(obs=bad)))


BAD_ENVELOPE_FIELDS: list[tuple[str, object]] = [
    ("kind", 1),
    ("sender", None),
    ("sender", b"s"),
    ("seq", "0"),
    ("seq", True),
    ("seq", 1.5),
    ("t", "now"),
    ("t", None),
    ("t", False),
    ("body", []),
    ("body", None),
    ("body", "x"),
]
FOREIGN: list[tuple[str, bytes, str]] = [
    *[
        (f"top-{type(x).__name__}-{i}", pack(x), "not-a-message")
        for i, x in enumerate([[], [1, 2, 3], 0, 1, -1, 2**64 - 1, 1.5, None, True, "chunk", b"raw", [{"v": 1}]])
    ],
    ("empty-map", pack({}), "version"),
    *[(f"v={v!r}", pack(envelope(raw_chunk_body(), v=v)), "version") for v in (0, 2, -1, "1", None, 1.5, [1])],
    ("only-v", pack({"v": 1}), "bad-envelope"),
    *[
        (f"no-{k}", pack({kk: vv for kk, vv in envelope({}).items() if kk != k}), "bad-envelope")
        for k in ("kind", "sender", "seq", "t", "body")
    ],
    *[(f"bad-{k}={v!r}", pack({**envelope({}), k: v}), "bad-envelope") for k, v in BAD_ENVELOPE_FIELDS],
    ("int-map-key", pack({1: 2}), "undecodable"),
    ("int-key-in-body", pack(envelope({1: 2})), "undecodable"),
    ("unknown-kind", pack(envelope({}, kind="chunkz")), "unknown-kind"),
    *[(f"chunk-no-{f}", pack(envelope(raw_chunk_body(**{f: None}))), "bad-chunk") for f in wire.CHUNK_FIELDS],
    ("chunk-lead", pack(envelope(raw_chunk_body(reward=ext(np.zeros((2, 4), np.float32))))), "bad-chunk"),
    ("chunk-obs-1d", _at_obs(ext(np.zeros(2, np.float32))), "bad-chunk"),
    ("chunk-obs-list", _at_obs([[1.0]]), "bad-chunk"),
    ("chunk-obs-timestamp", _at_obs(msgpack.Timestamp(1, 0)), "bad-chunk"),
    ("chunk-returns-str", pack(envelope({**raw_chunk_body(), "returns": "x"})), "bad-chunk"),
    ("weights-bad", pack(envelope({"version": 1}, kind="weights")), "bad-weights"),
    ("command-int-key", pack(envelope({"op": "x", "args": {"a": [{1: 2}]}}, kind="command")), "undecodable"),
    *[
        (f"dtype={d!r}", _at_obs(ext(d, [2, 3], b"\0" * 24)), "bad-array")
        for d in ("O", "|O", "<c8", ">f4", "float32", "f4", "", 5, None, b"<f4")
    ],
    ("bytes-short", _at_obs(ext("<f4", [2, 3], b"\0" * 23)), "bad-array"),
    ("bytes-long", _at_obs(ext("<f4", [2, 3], b"\0" * 25)), "bad-array"),
    ("bytes-for-empty", _at_obs(ext("<f4", [2, 0], b"\0" * 4)), "bad-array"),
    ("negative-dim", _at_obs(ext("<f4", [2, -3], b"\0" * 24)), "bad-array"),
    ("negative-dims", _at_obs(ext("<f4", [-2, -3], b"\0" * 24)), "bad-array"),
    ("nine-dims", _at_obs(ext("|u1", [1] * 9, b"\0")), "bad-array"),
    ("forty-dims", _at_obs(ext("|u1", [1] * 40, b"\0")), "bad-array"),
    ("bool-dim", _at_obs(ext("|u1", [True, 2], b"\0\0")), "bad-array"),
    ("float-dim", _at_obs(ext("|u1", [1.0, 2], b"\0\0")), "bad-array"),
    ("str-dim", _at_obs(ext("|u1", ["2"], b"\0\0")), "bad-array"),
    ("shape-int", _at_obs(ext("|u1", 2, b"\0\0")), "bad-array"),
    ("shape-map", _at_obs(ext("|u1", {"a": 2}, b"\0\0")), "bad-array"),
    ("shape-none", _at_obs(ext("|u1", None, b"")), "bad-array"),
    ("raw-str", _at_obs(ext("|u1", [2], "ab")), "bad-array"),
    ("raw-list", _at_obs(ext("|u1", [2], [0, 0])), "bad-array"),
    ("huge-zero-size", _at_obs(ext("<f4", [0, 2**63], b"")), "bad-array"),
    ("huge-dims", _at_obs(ext("<f4", [2**40, 2**40, 0], b"")), "bad-array"),
    ("huge-dim", _at_obs(ext("<f4", [2**64 - 1], b"")), "bad-array"),
    ("ext-int", _at_obs(msgpack.ExtType(wire.ARRAY_EXT, pack(5))), "bad-array"),
    ("ext-two", _at_obs(msgpack.ExtType(wire.ARRAY_EXT, pack(["<f4", [0]]))), "bad-array"),
    ("ext-four", _at_obs(msgpack.ExtType(wire.ARRAY_EXT, pack(["<f4", [0], b"", 1]))), "bad-array"),
    ("ext-garbage", _at_obs(msgpack.ExtType(wire.ARRAY_EXT, b"\xc1")), "bad-array"),
    ("ext-empty", _at_obs(msgpack.ExtType(wire.ARRAY_EXT, b"")), "bad-array"),
    ("ext-truncated", _at_obs(msgpack.ExtType(wire.ARRAY_EXT, pack(["<f4", [1], b"\0" * 4])[:-2])), "bad-array"),
    *[(f"ext-code-{c}", _at_obs(msgpack.ExtType(c, b"\0\0")), "unknown-ext") for c in (0, 2, 7, 127)],
    (
        "ext-code-7-in-args",
        pack(envelope({"op": "x", "args": {"a": msgpack.ExtType(7, b"")}}, "command")),
        "unknown-ext",
    ),
    (
        "timestamp-bad-len",
        _at_obs(msgpack.ExtType(5, b"abc")).replace(b"\xc7\x03\x05abc", b"\xc7\x03\xffabc"),
        "undecodable",
    ),
    ("trailing-byte", wire.encode("chunk", make_chunk(), "s") + b"\0", "undecodable"),
    ("two-messages", wire.encode("chunk", make_chunk(), "s") * 2, "undecodable"),
    ("bad-utf8", pack(envelope({})).replace(b"\xa6sender\xa1s", b"\xa6sender\xa1\xff"), "undecodable"),
    ("too-deep", b"\x91" * 5000 + b"\x00", "undecodable"),
    ("empty", b"", "undecodable"),
    ("reserved-byte", b"\xc1", "undecodable"),
]


@pytest.mark.parametrize(("payload", "reason"), [pytest.param(p, r, id=n) for n, p, r in FOREIGN])
def test_decode_refuses_foreign_payloads_with_their_reason(payload: bytes, reason: str) -> None:
    with pytest.raises(WireError) as info:
        wire.decode(payload)
    assert info.value.reason == reason, str(info.value)


@FAST
@given(st.binary(max_size=512))
def test_decode_of_random_bytes_raises_only_wire_error(data: bytes) -> None:
    try:
        wire.decode(data)
    except WireError as exc:
        assert exc.reason
    # (a random payload that happens to be a valid message would be fine too)


@pytest.mark.parametrize("kind", KINDS)
@settings(FAST, max_examples=25)
@given(data=st.data())
def test_every_truncation_of_a_valid_message_is_undecodable(kind: str, data: st.DataObject) -> None:
    payload = wire.encode(kind, data.draw(BODIES[kind]), "s")
    for cut in range(len(payload)):
        with pytest.raises(WireError) as info:
            wire.decode(payload[:cut])
        assert info.value.reason == "undecodable"


# -------------------------------------------------------------------------------------------------- garbage
N_GARBAGE = 10_000


def garbage(seed: int = 1234) -> list[tuple[bytes, str | None]]:
    """N_GARBAGE bad payloads for an inbox of chunks, each with its drop reason where that is known."""
    rng = np.random.default_rng(seed)
    out: list[tuple[bytes, str | None]] = [(p, r) for _, p, r in FOREIGN]
    # every bad array in every chunk field, not only obs
    bad_arrays = [
        ext("O", [2, 3], b"\0" * 24),
        ext("<f4", [2, 3], b"\0" * 20),
        ext("<f4", [2, -3], b"\0" * 24),
        ext("|u1", [1] * 9, b"\0"),
        msgpack.ExtType(7, b"\0" * 8),
        msgpack.ExtType(wire.ARRAY_EXT, b"\xc1"),
    ]
    for field in wire.CHUNK_FIELDS:
        for i, bad in enumerate(bad_arrays):
            out.append(
                (pack(envelope(raw_chunk_body(**{field: bad}), seq=i)), "unknown-ext" if i == 4 else "bad-array")
            )
    # valid messages of the other kinds
    for i in range(100):
        weights = wire.weights_body(i, "dqn", {"w": rng.random((3, 2))})
        out.append((wire.encode("weights", weights, "l"), "unexpected-weights"))
        budget = {"allowed_steps": i, "ingested_steps": 0, "version": i}
        out.append((wire.encode("budget", budget, "l"), "unexpected-budget"))
        out.append((wire.encode("metrics", wire.metrics_body("actor", f"a{i}", {"x": i}), "a"), "unexpected-metrics"))
        out.append((wire.encode("command", {"op": "stop", "args": {"i": i}}, "api"), "unexpected-command"))
    # truncations: a small chunk at every cut point, a large one at random cut points
    small = wire.encode("chunk", make_chunk(2, 2, 3), "a0", seq=1)
    out += [(small[:cut], "undecodable") for cut in range(len(small))]
    large = wire.encode("chunk", make_chunk(64, 3, 32, seed=1), "a0", seq=2)
    out += [(large[:cut], "undecodable") for cut in rng.choice(len(large), 1500, replace=False)]
    # random bytes (reason unknown): short, medium and long; some after a msgpack map header to get further in
    while len(out) < N_GARBAGE:
        n = int(rng.choice([rng.integers(0, 8), rng.integers(8, 256), rng.integers(256, 4096)]))
        head = b"\x86" if rng.random() < 0.25 else b""
        out.append((head + rng.integers(0, 256, n, dtype=np.uint8).tobytes(), None))
    assert len(out) == N_GARBAGE
    order = rng.permutation(len(out))
    return [out[i] for i in order]


def test_ten_thousand_garbage_payloads_into_one_inbox() -> None:
    payloads = garbage()
    box = Inbox(kinds={"chunk"})
    known = collections.Counter(r for _, r in payloads if r is not None)
    for payload, reason in payloads:
        drops, by_reason = box.drops, box.dropped[reason] if reason else 0
        assert box.offer(payload) is None
        assert box.drops == drops + 1  # exactly one drop per payload
        if reason is not None:
            assert box.dropped[reason] == by_reason + 1, (reason, payload[:64])
    assert box.drops == N_GARBAGE
    assert sum(box.dropped.values()) == N_GARBAGE
    assert len(box) == 0 and box.received == 0
    assert box.get() is None and box.drain() == [] and box.latest() is None
    assert "internal" not in box.dropped and "overflow" not in box.dropped
    for reason, n in known.items():
        assert box.dropped[reason] >= n, reason
    for kind in ("weights", "budget", "metrics", "command"):
        assert box.dropped[f"unexpected-{kind}"] == known[f"unexpected-{kind}"] == 100
    assert box.dropped["undecodable"] > 2000  # the truncations and most random bytes
    # still working afterwards
    msg = box.offer(wire.encode("chunk", make_chunk(), "a0", seq=99))
    assert msg is not None and msg.seq == 99
    assert len(box) == 1 and box.received == 1 and box.drops == N_GARBAGE
    assert box.get() is msg


def test_garbage_is_deterministic(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(wire, "time", SimpleNamespace(time=lambda: 1.0e9))  # the envelope's send time
    assert garbage() == garbage()


# --------------------------------------------------------------------------------------------------- inbox
def seq_of(msg: wire.Message | None) -> int:
    """The sequence number of a message the inbox kept (None: it dropped it)."""
    assert msg is not None, "dropped"
    return msg.seq


def chunk_payload(seq: int) -> bytes:
    return wire.encode("chunk", make_chunk(1, 1, 2), "a0", seq=seq)


class Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class Sample:
    def __init__(self, data: bytes) -> None:
        self.payload = Payload(data)


class DeleteSample:
    @property
    def payload(self) -> Any:
        raise RuntimeError("a delete has no payload")


def test_inbox_overflow_drops_the_oldest() -> None:
    box = Inbox(kinds={"chunk"}, maxlen=3)
    for seq in range(5):
        assert seq_of(box.offer(chunk_payload(seq))) == seq
    assert len(box) == 3
    assert box.dropped == collections.Counter(overflow=2) and box.drops == 2
    assert box.received == 5
    assert [m.seq for m in box.drain()] == [2, 3, 4]
    assert len(box) == 0 and box.drain() == []


def test_inbox_get_is_fifo_and_latest_keeps_only_the_newest() -> None:
    box = Inbox(kinds={"chunk", "weights"})
    for seq in range(4):
        box.offer(chunk_payload(seq))
    assert seq_of(box.get()) == 0 and seq_of(box.get(timeout=1)) == 1
    assert seq_of(box.latest()) == 3
    assert len(box) == 0 and box.latest() is None and box.get() is None
    w = box.offer(wire.encode("weights", wire.weights_body(1, "x", {}), "l"))
    assert w is not None and w.kind == "weights" and box.latest() is w


def test_inbox_keeps_only_its_kinds() -> None:
    box = Inbox(kinds=["weights"])
    assert box.offer(chunk_payload(0)) is None
    assert box.dropped == collections.Counter({"unexpected-chunk": 1})
    assert len(box) == 0 and box.received == 0


def test_inbox_get_times_out_with_none() -> None:
    box = Inbox(kinds={"chunk"})
    start = time.monotonic()
    assert box.get() is None and box.get(timeout=0) is None
    assert time.monotonic() - start < 0.05  # no timeout: no wait
    start = time.monotonic()
    assert box.get(timeout=0.1) is None
    assert 0.09 <= time.monotonic() - start < 2.0


def test_inbox_get_wakes_up_when_a_message_arrives() -> None:
    box = Inbox(kinds={"chunk"})
    timer = threading.Timer(0.05, box.offer, args=(chunk_payload(7),))
    timer.start()
    try:
        start = time.monotonic()
        msg = box.get(timeout=10)
        assert msg is not None and msg.seq == 7
        assert time.monotonic() - start < 5
    finally:
        timer.join()


def test_inbox_as_a_zenoh_callback() -> None:
    box = Inbox(kinds={"chunk"})
    box(Sample(chunk_payload(1)))
    assert len(box) == 1 and box.received == 1
    box(Sample(b"\xc1"))
    box(DeleteSample())
    box(SimpleNamespace(payload=None))  # to_bytes missing: AttributeError
    box(SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: 1 / 0)))
    assert box.dropped == collections.Counter({"no-payload": 3, "undecodable": 1})
    assert seq_of(box.get()) == 1


def test_inbox_callback_with_a_real_zbytes_payload() -> None:
    zenoh = pytest.importorskip("zenoh")
    box = Inbox(kinds={"chunk"})
    box(SimpleNamespace(payload=zenoh.ZBytes(chunk_payload(3))))
    assert seq_of(box.get()) == 3 and box.drops == 0


def test_inbox_never_raises_even_when_decode_does(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(payload: bytes) -> None:
        raise RuntimeError("bug")

    monkeypatch.setattr(inbox_mod, "decode", broken)
    box = Inbox(kinds={"chunk"})
    assert box.offer(chunk_payload(0)) is None
    box(Sample(chunk_payload(0)))
    assert box.dropped == collections.Counter(internal=2)


def test_inbox_accepts_bytes_like_payloads() -> None:
    box = Inbox(kinds={"chunk"})
    payload = chunk_payload(5)
    assert seq_of(box.offer(bytearray(payload))) == 5
    assert seq_of(box.offer(memoryview(payload))) == 5
    assert len(box) == 2


def test_inbox_counts_stay_consistent_under_concurrency() -> None:
    box = Inbox(kinds={"chunk"}, maxlen=64)
    good, bad = chunk_payload(0), b"\x93\x01"
    n_threads, per_thread = 4, 250
    got: list[int] = []
    done = threading.Event()

    def produce() -> None:
        for i in range(per_thread):
            box.offer(good if i % 2 else bad)

    def consume() -> None:
        while not done.is_set() or len(box):
            if box.get(timeout=0.01) is not None:
                got.append(1)

    consumer = threading.Thread(target=consume)
    consumer.start()
    producers = [threading.Thread(target=produce) for _ in range(n_threads)]
    for t in producers:
        t.start()
    for t in producers:
        t.join()
    done.set()
    consumer.join(timeout=10)
    assert not consumer.is_alive()
    n_good = n_threads * per_thread // 2
    assert box.received == n_good
    assert box.dropped["undecodable"] == n_good
    assert len(got) + box.dropped["overflow"] == n_good
    assert box.drops == n_good + box.dropped["overflow"]


# ---------------------------------------------------------------------------------------------------- keys
def test_key_shapes() -> None:
    assert keys.job_root("j1") == "convoy/j1"
    assert keys.exp("j1", "actor-0") == "convoy/j1/exp/actor-0"
    assert keys.exp_all("j1") == "convoy/j1/exp/*"
    assert keys.weights("j1") == "convoy/j1/weights"
    assert keys.ctl("j1", "budget") == "convoy/j1/ctl/budget"
    assert keys.metrics("j1", "learner", "l.0") == "convoy/j1/metrics/learner/l.0"
    assert keys.metrics_all("j1") == "convoy/j1/metrics/**"
    assert keys.alive("j1", "actor", "a_3") == "convoy/j1/alive/actor/a_3"
    assert keys.alive_all("j1") == "convoy/j1/alive/**"
    assert keys.host("gpu-box", "cmd") == "convoy/hosts/gpu-box/cmd"
    assert keys.PREFIX == "convoy"
    for role in keys.ROLES:
        assert keys.check_id(role) == role


def test_wildcard_keys_cover_the_concrete_keys() -> None:
    zenoh = pytest.importorskip("zenoh")
    pairs = [
        (keys.exp_all("j"), keys.exp("j", "a1")),
        (keys.metrics_all("j"), keys.metrics("j", "actor", "a1")),
        (keys.alive_all("j"), keys.alive("j", "learner", "l0")),
    ]
    for pattern, key in pairs:
        assert zenoh.KeyExpr(pattern).intersects(zenoh.KeyExpr(key)), (pattern, key)
    assert not zenoh.KeyExpr(keys.exp_all("j")).intersects(zenoh.KeyExpr(keys.exp("k", "a1")))
    assert not zenoh.KeyExpr(keys.exp_all("j")).intersects(zenoh.KeyExpr(keys.weights("j")))


UNSAFE = ["*", "**", "$x", "a$", "a/b", "/", "", "a" * 65, "a*", "-a", ".", "..", "_a", "a b", "a#b", "a?b", "é"]
UNSAFE += ["abc\n", "abc\r", "\nabc", "a\tb", "a\0b"]


@pytest.mark.parametrize("value", UNSAFE, ids=repr)
def test_check_id_rejects_unsafe_ids(value: str) -> None:
    with pytest.raises(ValueError) as info:
        keys.check_id(value, "actor id")
    message = str(info.value)
    assert message.startswith(f"actor id {value!r} ")
    assert "key expression" in message


@pytest.mark.parametrize(
    "value", [None, 5, 1.5, b"abc", ["a"], object()], ids=lambda v: type(v).__name__ if type(v) is object else repr(v)
)  # the same ids in every process (an object's repr holds its address): pytest-xdist compares them
def test_check_id_rejects_non_str(value: Any) -> None:
    with pytest.raises(ValueError, match=r"^job id "):
        keys.check_id(value, "job id")


@pytest.mark.parametrize("value", ["a", "0", "A1_b.c-d", "a" * 64, "actor-0", "host.example.com", "x..y"])
def test_check_id_accepts_safe_ids(value: str) -> None:
    assert keys.check_id(value) == value


BUILDERS = [
    (lambda v: keys.job_root(v), "job id"),
    (lambda v: keys.exp(v, "a"), "job id"),
    (lambda v: keys.exp("j", v), "actor id"),
    (lambda v: keys.exp_all(v), "job id"),
    (lambda v: keys.weights(v), "job id"),
    (lambda v: keys.ctl("j", v), "control name"),
    (lambda v: keys.metrics("j", v, "x"), "role"),
    (lambda v: keys.metrics("j", "actor", v), "process id"),
    (lambda v: keys.metrics_all(v), "job id"),
    (lambda v: keys.alive("j", v, "x"), "role"),
    (lambda v: keys.alive("j", "actor", v), "process id"),
    (lambda v: keys.alive_all(v), "job id"),
    (lambda v: keys.host(v, "cmd"), "host name"),
    (lambda v: keys.host("h", v), "host endpoint"),
]


@pytest.mark.parametrize(("build", "what"), BUILDERS)
@pytest.mark.parametrize("value", ["*", "**", "a/b", "$x", "", "ok\n"], ids=repr)
def test_every_builder_checks_every_id(build: Any, what: str, value: str) -> None:
    with pytest.raises(ValueError, match=rf"^{what} "):
        build(value)
    assert build("ok").count("/") >= 1  # and builds with a safe one


SAFE_IDS = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", fullmatch=True)


@FAST
@given(job=SAFE_IDS, role=SAFE_IDS, ident=SAFE_IDS)
def test_parse_alive_round_trips(job: str, role: str, ident: str) -> None:
    key = keys.alive(job, role, ident)
    assert keys.parse_alive(key) == (job, role, ident)
    assert keys.parse_alive(keys.metrics(job, role, ident)) is None
    assert keys.parse_alive(keys.exp(job, ident)) is None


class KeyLike:
    """Like zenoh.KeyExpr: a key is whatever str() of it says."""

    def __init__(self, key: str) -> None:
        self.key = key

    def __str__(self) -> str:
        return self.key


@pytest.mark.parametrize(
    "key",
    [
        "",
        "convoy",
        "convoy/j",
        "convoy/j/alive",
        "convoy/j/alive/actor",
        "convoy/j/alive/actor/a/extra",
        "other/j/alive/actor/a",
        "convoy/j/exp/a",
        "convoy/j/metrics/actor/a",
        "convoy/j/weights",
        "convoy/hosts/h/cmd",
        "convoy/j/Alive/actor/a",
    ],
)
def test_parse_alive_rejects_other_keys(key: str) -> None:
    assert keys.parse_alive(key) is None


def test_parse_alive_takes_key_expressions() -> None:
    assert keys.parse_alive(KeyLike("convoy/j/alive/actor/a0")) == ("j", "actor", "a0")
    zenoh = pytest.importorskip("zenoh")
    assert keys.parse_alive(zenoh.KeyExpr(keys.alive("j", "learner", "l0"))) == ("j", "learner", "l0")


# ------------------------------------------------------------------------------------------------------ size
def test_chunk_size_is_raw_bytes_plus_a_constant() -> None:
    """Arrays travel as one buffer each: no per-element encoding (not timed)."""
    body = make_chunk(t=1024, b=3, obs_dim=32)
    raw = sum(a.nbytes for a in body["arrays"].values())
    assert body["arrays"]["obs"].shape == (1024, 3, 32) and body["arrays"]["obs"].dtype == np.float32
    payload = wire.encode("chunk", body, "actor-0", seq=1)
    assert raw < len(payload) <= raw * 1.05 + 512
    assert len(payload) - raw < 1024  # in fact a small constant: envelope + a header per array
    doubled = wire.encode("chunk", make_chunk(t=2048, b=3, obs_dim=32), "actor-0", seq=1)
    assert abs((len(doubled) - 2 * raw) - (len(payload) - raw)) < 64  # overhead does not grow with T
    msg = wire.decode(payload)
    obs = msg.body["arrays"]["obs"]
    assert not obs.flags.owndata and not obs.flags.writeable  # a view on the received bytes, not a copy
    assert np.array_equal(obs, body["arrays"]["obs"])


def test_a_root_gets_a_private_job_credential_and_a_joining_peer_keeps_the_users(tmp_path) -> None:
    import stat

    from convoy.protocol.session import ZenohSettings, read_credentials, zenoh_config

    root = ZenohSettings().secured(tmp_path, "job-1").rooted()
    assert root.user == "job-1" and root.credentials_file == str(tmp_path / "zenoh-credentials")
    assert stat.S_IMODE((tmp_path / "zenoh-credentials").stat().st_mode) == 0o600
    user, password = read_credentials(root.credentials_file)
    assert root.password is not None
    assert (user, password.get_secret_value()) == ("job-1", root.password.get_secret_value())
    assert len(password.get_secret_value()) >= 32  # 24 random bytes
    child = root.child()
    assert (child.user, child.password, child.credentials_file) == (root.user, root.password, root.credentials_file)
    # the root is its children's router and they are its clients: each link is opened once (zenoh#2577)
    assert (root.mode, child.mode, child.connect, child.listen) == ("router", "client", root.listen, ())
    config = str(zenoh_config(root))
    assert "dictionary_file" in config and password.get_secret_value() not in repr(root)
    joining = ZenohSettings(connect=("tcp/10.0.0.5:7447",))
    assert joining.secured(tmp_path, "job-1") == joining  # another's network: the user's own credentials
    given = ZenohSettings(user="alice", password="secret")
    assert given.secured(tmp_path, "job-1") == given
    with pytest.raises(ValueError, match="usrpwd user"):
        ZenohSettings().secured(tmp_path, "a:b")
