"""The wire schema: every message between Convoy processes, encoded and validated here and nowhere else.

A message is a msgpack map ``{v, kind, sender, seq, t, body}``. numpy arrays inside ``body`` travel as a msgpack
extension (code 1) holding ``[dtype, shape, raw bytes]``: one buffer copy per array, no per-element Python work,
and decoding is ``np.frombuffer`` (a read-only view on the received bytes). Anything that fails to decode or to
validate raises :class:`WireError` — receivers count it and drop the message (:class:`protocol.inbox.Inbox`); a
corrupt, truncated or foreign payload never reaches a process's logic.

Kinds and their bodies:

* ``chunk`` (actor → learner): ``arrays`` (the joint transitions ``[T, B, …]``: ``obs, action, reward, next_obs,
  terminated, truncated, episode`` plus the algorithm's extras), ``actor``, ``policy_version``, ``env_steps``,
  ``returns`` (mean-over-agents returns of episodes finished in the chunk). DIAL's on-policy sequences are chunks
  with T = its unroll length, so one kind serves transition batches and episode batches. A population's chunk
  holds its R runs' envs run by run (B = R × envs per run) and says each return's run in ``return_runs``.
* ``weights`` (learner → actors): ``version``, ``algo``, ``state`` (name → array).
* ``budget`` (learner → actors): ``allowed_steps`` (env steps the actors may have sent in all: those ingested, plus
  the slack, less what still waits in the learner's queue; the job's ``steps`` once it has them), ``ingested_steps``,
  ``version`` — the samples-per-insert throttle.
* ``metrics`` (any → supervisor/API): ``role``, ``id``, ``values`` (name → number).
* ``command`` (supervisor/API → host agents; a job runner's ``stop`` → its actors): ``op`` and ``args``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, SupportsFloat, SupportsIndex, TypeGuard

import msgpack
import numpy as np

from convoy.transition import TRANSITION

VERSION = 1
ARRAY_EXT = 1
MAX_DIMS = 8
DTYPES = frozenset(
    np.dtype(t).str for t in ("bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64")
) | frozenset(np.dtype(t).str for t in ("float16", "float32", "float64"))
CHUNK_FIELDS = tuple(TRANSITION)  # every chunk carries the declared transition; algorithms may add fields


class WireError(ValueError):
    """A payload that is not a valid Convoy message; ``reason`` is a short label for the drop counters."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass(frozen=True)
class Message:
    kind: str
    sender: str
    seq: int
    t: float
    body: dict[str, Any]


# ------------------------------------------------------------------------------------------------------ arrays
def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        arr = np.asarray(obj, order="C")  # not ascontiguousarray: that turns a 0-d array into shape (1,)
        if arr.dtype.str not in DTYPES:
            raise TypeError(f"array dtype {arr.dtype} is not sent on the wire; use one of {sorted(DTYPES)}")
        if arr.ndim > MAX_DIMS:
            raise TypeError(f"array with {arr.ndim} dims is not sent on the wire (at most {MAX_DIMS})")
        raw = arr.data.cast("B") if arr.size else b""  # the array's own buffer (a memoryview), as bytes
        return msgpack.ExtType(ARRAY_EXT, msgpack.packb([arr.dtype.str, list(arr.shape), raw]))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, int):  # msgpack hands over the ints it cannot pack
        raise TypeError(f"integer {obj} is outside msgpack's 64-bit range")
    raise TypeError(f"cannot send {type(obj).__name__} on the wire")


def _ext_hook(code: int, data: bytes) -> Any:
    if code != ARRAY_EXT:
        raise WireError("unknown-ext", f"extension type {code}")
    try:
        dtype, shape, raw = msgpack.unpackb(data, raw=False, use_list=True)
    except Exception:
        raise WireError("bad-array", "array extension is not [dtype, shape, raw]") from None
    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise WireError("bad-array", f"dtype {dtype!r}")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_DIMS
        or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
    ):
        raise WireError("bad-array", f"shape {shape!r}")
    if not isinstance(raw, bytes) or math.prod(shape) * np.dtype(dtype).itemsize != len(raw):
        raise WireError("bad-array", f"{len(raw) if isinstance(raw, bytes) else '?'} bytes for {dtype}{shape}")
    try:
        return np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape)
    except ValueError as exc:  # e.g. a zero-size shape with a dimension numpy cannot index
        raise WireError("bad-array", str(exc)) from None


# ----------------------------------------------------------------------------------------------- encode/decode
def encode(kind: str, body: dict[str, Any], sender: str, seq: int = 0) -> bytes:
    """One message as bytes (``body`` validated first, so a sender cannot emit what receivers would drop)."""
    if not isinstance(body, dict):
        raise WireError("bad-envelope", "body is not a map")
    validate(kind, body)
    if not isinstance(sender, str):
        raise WireError("bad-envelope", f"sender {sender!r} is not a str")
    packed: bytes = msgpack.packb(
        {"v": VERSION, "kind": kind, "sender": sender, "seq": int(seq), "t": time.time(), "body": body},
        default=_default,
        use_bin_type=True,
    )
    return packed


def decode(data: bytes | bytearray | memoryview) -> Message:
    """The message in ``data``, or :class:`WireError` saying why not."""
    try:
        obj = msgpack.unpackb(data, raw=False, ext_hook=_ext_hook, strict_map_key=True)
    except WireError:
        raise
    except Exception as exc:  # msgpack raises several types for truncated / garbage input
        raise WireError("undecodable", type(exc).__name__) from None
    if not isinstance(obj, dict):
        raise WireError("not-a-message", type(obj).__name__)
    if obj.get("v") != VERSION:
        raise WireError("version", f"schema version {obj.get('v')!r}, this process speaks {VERSION}")
    kind, sender, seq, t, body = (obj.get(k) for k in ("kind", "sender", "seq", "t", "body"))
    if not isinstance(kind, str) or not isinstance(sender, str) or not _is_int(seq) or not _is_num(t):
        raise WireError("bad-envelope", "kind, sender, seq or t missing or mistyped")
    if not isinstance(body, dict):
        raise WireError("bad-envelope", "body is not a map")
    validate(kind, body)
    return Message(kind, sender, int(seq), float(t), body)


# -------------------------------------------------------------------------------------------------- validation
def _is_int(x: object) -> TypeGuard[int]:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x: object) -> TypeGuard[int | float]:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _need(body: dict[str, Any], kind: str, **fields: Any) -> None:
    for name, check in fields.items():
        if name not in body or not check(body[name]):
            raise WireError(f"bad-{kind}", f"field {name!r} missing or mistyped")


def _map_keys(x: Any) -> bool:
    """Every map inside ``x`` keyed by str or bytes, as receivers' ``strict_map_key`` demands (iterative: msgpack
    nests deeper than Python's recursion limit)."""
    stack = [x]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            if not all(isinstance(k, str | bytes) for k in item):
                return False
            stack.extend(item.values())
        elif isinstance(item, list | tuple):
            stack.extend(item)
    return True


def _arrays(x: Any) -> bool:
    return isinstance(x, dict) and all(isinstance(k, str) and isinstance(v, np.ndarray) for k, v in x.items())


def validate(kind: str, body: dict[str, Any]) -> None:
    """Check ``body`` against ``kind``'s schema; WireError on the first problem."""
    if kind == "chunk":
        _need(
            body,
            kind,
            arrays=_arrays,
            actor=lambda x: isinstance(x, str),
            policy_version=_is_int,
            env_steps=_is_int,
            returns=lambda x: isinstance(x, list) and all(_is_num(r) for r in x),
        )
        runs = body.get("return_runs")
        if runs is not None and not (
            isinstance(runs, list) and len(runs) == len(body["returns"]) and all(_is_int(r) for r in runs)
        ):
            raise WireError("bad-chunk", "return_runs must be one int per return")
        arrays = body["arrays"]
        missing = [f for f in CHUNK_FIELDS if f not in arrays]
        if missing:
            raise WireError("bad-chunk", f"arrays {missing} missing")
        lead = arrays["obs"].shape[:2]
        if len(lead) != 2 or any(a.ndim < 2 or a.shape[:2] != lead for a in arrays.values()):
            raise WireError("bad-chunk", "arrays must share leading dims [T, B]")
    elif kind == "weights":
        _need(body, kind, version=_is_int, algo=lambda x: isinstance(x, str), state=_arrays)
    elif kind == "budget":
        _need(body, kind, allowed_steps=_is_int, ingested_steps=_is_int, version=_is_int)
    elif kind == "metrics":
        _need(
            body,
            kind,
            role=lambda x: isinstance(x, str),
            id=lambda x: isinstance(x, str),
            values=lambda x: isinstance(x, dict) and all(isinstance(k, str) and _is_num(v) for k, v in x.items()),
        )
    elif kind == "command":
        _need(body, kind, op=lambda x: isinstance(x, str), args=lambda x: isinstance(x, dict) and _map_keys(x))
    else:
        raise WireError("unknown-kind", repr(kind))


# ------------------------------------------------------------------------------------------ typed constructors
def chunk_body(
    arrays: dict[str, np.ndarray],
    actor: str,
    policy_version: SupportsIndex,
    env_steps: SupportsIndex,
    returns: Sequence[SupportsFloat],
    return_runs: Sequence[SupportsIndex] | None = None,
) -> dict[str, Any]:
    """A chunk's body; numpy scalars are taken and sent as plain ints and floats."""
    body = {
        "arrays": arrays,
        "actor": actor,
        "policy_version": int(policy_version),
        "env_steps": int(env_steps),
        "returns": [float(r) for r in returns],
    }
    if return_runs is not None:  # each return's run (R ≥ 1 runs' envs, run by run)
        body["return_runs"] = [int(r) for r in return_runs]
    return body


def weights_body(version: SupportsIndex, algo: str, state: dict[str, np.ndarray]) -> dict[str, Any]:
    return {"version": int(version), "algo": algo, "state": state}


DROPPED_PREFIX = "dropped_"  # a metrics value ``dropped_<reason>``: messages that process refused so far, by reason


def dropped_reasons(values: dict[str, float]) -> dict[str, int]:
    """The ``dropped_<reason>`` counts of one metrics message's values, as {reason: count} (bad values skipped)."""
    out: dict[str, int] = {}
    for key, value in values.items():
        if key.startswith(DROPPED_PREFIX) and isinstance(value, int | float) and 0 <= value < 2**53:
            out[key[len(DROPPED_PREFIX) :]] = int(value)
    return out


def metrics_body(role: str, ident: str, values: Mapping[str, object]) -> dict[str, Any]:
    """A metrics body of ``values``' numbers (numpy's too, sent as floats); anything else is left out."""
    return {
        "role": role,
        "id": ident,
        "values": {k: float(v) for k, v in values.items() if _is_num(v) or isinstance(v, np.integer | np.floating)},
    }
