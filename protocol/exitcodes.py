"""Exit codes of Convoy's worker processes, which supervisors (``services.procs``) act on.

0 means the process finished its part of the job (actor: the learner has all the data, or a stop came; learner: the
job is done) and is not restarted — except an actor that exits 0 while its local learner lacks the job's steps (a
forged stop or budget): it is respawned (``services.procs``). ``STOPPED`` (143, the shell's code for SIGTERM) means a
signal stopped it before that — a supervisor that still wants the process starts it again, like after any other crash.
"""

import sys

DONE = 0
NO_DATA = 3  # the learner heard no chunk for runtime.data_timeout_s: a crash the supervisor handles and counts
DIVERGED = 4  # non-finite losses in a row: a restart from the checkpoint would diverge again; the job fails
CONFIG = 78  # the process refused the job's configuration (a ConfigError; sysexits' EX_CONFIG): a restart would
# refuse it again, so the job fails at once with the refusal as its error
STOPPED = 143
ORPHAN_EXIT_S = 60.0  # how long an orphaned worker may take to save and close before it is made to exit


class ParentWatch:
    """Notices when the process that started this one has died: a worker whose supervisor was killed must not wait
    for ever for a learner or actors that will never come back.

    A multiprocessing child watches its parent's sentinel (``multiprocessing.parent_process()``): that is the
    supervisor even when the child was forked by a forkserver, whose own lifetime the child's open descriptors
    extend — re-parenting would never show. Anything else (``convoy actor`` from a shell) watches its parent PID.
    """

    def __init__(self, exit_after_s: float = ORPHAN_EXIT_S) -> None:
        import multiprocessing
        import os
        import time

        self._os, self._time = os, time
        self._mp_parent = multiprocessing.parent_process()
        self.parent = os.getppid()
        self._next = 0.0
        self.exit_after_s = exit_after_s

    def orphaned(self) -> bool:
        """True once the parent is gone; checks at most once a second (cheap enough for a hot loop)."""
        now = self._time.monotonic()
        if now < self._next:
            return False
        self._next = now + 1.0
        gone = not self._mp_parent.is_alive() if self._mp_parent is not None else self._os.getppid() != self.parent
        if gone:
            import faulthandler

            # the worker now saves and closes; should anything hang there (a write on a starved disk, a transport
            # that will not close), this C-level timer prints every thread's stack and exits without the GIL
            faulthandler.dump_traceback_later(self.exit_after_s, exit=True, file=sys.__stderr__ or 2)
        return gone


def dump_stacks_on_sigusr1() -> None:
    """``kill -USR1 PID`` prints every thread's Python stack to the process's stderr (the job's log): how to see
    where a worker that will not exit, or will not progress, is waiting."""
    import faulthandler
    import signal

    if hasattr(signal, "SIGUSR1"):  # to fd 2 itself: sys.stderr may be a stream without one (a test's capture)
        faulthandler.register(signal.SIGUSR1, file=sys.__stderr__ or 2, all_threads=True)
