"""Where Zenoh callbacks hand messages to a process: decode, validate, count, queue — never block, never raise.

Zenoh runs subscriber callbacks on its own threads; anything slow or raising there stalls the network. An
:class:`Inbox` decodes the payload (:func:`protocol.wire.decode`), keeps only the kinds it was made for, and puts
the message on a bounded queue; a full queue drops the *oldest* message (the newest weights or transitions are
worth more), and every drop is counted by reason so that metrics can show it.
"""

from __future__ import annotations

import collections
import threading
from collections.abc import Iterable
from typing import Any

from convoy.protocol.wire import Message, WireError, decode


class Inbox:
    def __init__(self, kinds: Iterable[str], maxlen: int = 1024) -> None:
        self.kinds = frozenset(kinds)
        self._q: collections.deque[Message] = collections.deque(maxlen=maxlen)
        self._cv = threading.Condition()
        self.received = 0
        self.dropped: collections.Counter[str] = collections.Counter()

    def __call__(self, sample: Any) -> None:
        """The Zenoh subscriber callback."""
        try:
            payload = sample.payload.to_bytes()
        except Exception:  # a sample without a payload (e.g. a delete)
            self._drop("no-payload")
            return
        self.offer(payload)

    def offer(self, payload: bytes | bytearray | memoryview) -> Message | None:
        """Decode and queue ``payload``; returns the message, or None when it was dropped."""
        try:
            msg = decode(payload)
        except WireError as exc:
            self._drop(exc.reason)
            return None
        except Exception:  # belt and braces: nothing escapes into Zenoh's thread
            self._drop("internal")
            return None
        if msg.kind not in self.kinds:
            self._drop(f"unexpected-{msg.kind}")
            return None
        with self._cv:
            if len(self._q) == self._q.maxlen:
                self.dropped["overflow"] += 1
            self._q.append(msg)
            self.received += 1
            self._cv.notify()
        return msg

    def _drop(self, reason: str) -> None:
        with self._cv:
            self.dropped[reason] += 1

    def get(self, timeout: float | None = None) -> Message | None:
        """The oldest queued message, waiting up to ``timeout`` seconds (None = don't wait)."""
        with self._cv:
            if not self._q and timeout:
                self._cv.wait(timeout)
            return self._q.popleft() if self._q else None

    def drain(self) -> list[Message]:
        with self._cv:
            out = list(self._q)
            self._q.clear()
            return out

    def latest(self) -> Message | None:
        """The newest message, discarding older ones (weights: only the newest matters)."""
        with self._cv:
            msg = self._q[-1] if self._q else None
            self._q.clear()
            return msg

    @property
    def drops(self) -> int:
        return sum(self.dropped.values())

    def __len__(self) -> int:
        return len(self._q)
