"""A process pool that leaves nothing behind: what ``generate`` and the experiments run in.

Three ways a plain ``ProcessPoolExecutor`` leaks or shouts:
- SIGKILL of the parent: the workers are orphaned and run their task to the end (minutes, hundreds
  of MB each). Here each worker watches its parent and exits as soon as it is gone.
- SIGTERM or Ctrl-C in the parent: leaving the ``with`` block waits for the running tasks. Here an
  exception (KeyboardInterrupt included) terminates the workers at once and re-raises.
- Ctrl-C reaches the whole process group: every worker prints its own KeyboardInterrupt
  traceback, some while still importing. Here workers are started with SIGINT blocked (the mask
  survives exec), so only the parent sees it, and the parent tears the pool down; a signal that
  arrives while a worker is being started waits until it is (``signals_held``).

Workers are spawned, never forked: zarr's event loop thread must not be copied.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing as mp
import os
import signal
import threading
import time
from typing import Any, Callable, Iterator

PARENT_POLL_S = 0.5
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held until the block ends, where one that arrived meanwhile takes effect
    (its handler runs: KeyboardInterrupt, ``Terminated``). A process started within is wholly
    started and registered, or never was: one interrupted half-way gets its start-up data cut off
    and prints ``EOFError`` from ``multiprocessing.spawn``, outside the pool that would stop it.

    Two layers, as the signal may reach any thread: SIGINT is blocked in this thread, so processes
    started now inherit it blocked (Ctrl-C to the process group reaches the parent alone); and the
    Python handlers are swapped for ones that only note the signal, since a signal another thread
    received still runs its handler in this one, at the next bytecode."""
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    deferred = {sig: h for sig, h in handlers.items() if callable(h)}  # Python handlers; not SIG_IGN/SIG_DFL
    for sig in deferred:
        signal.signal(sig, lambda signum, frame: arrived.append(signum))
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)  # a blocked SIGINT arrives here, deferred
        for sig, handler in deferred.items():
            signal.signal(sig, handler)
        for signum in dict.fromkeys(arrived):  # several within the hold (milliseconds) act as one
            deferred[signum](signum, None)


class WorkerPool:
    """A spawn-context process pool of ``workers`` processes, each running ``initializer(*initargs)``
    first; one BLAS/OpenMP thread per worker (the workers already fill the cores)."""

    def __init__(self, workers: int, initializer: Callable | None = None, initargs: tuple = ()):
        self.context = mp.get_context("spawn")
        self._pool = cf.ProcessPoolExecutor(workers, mp_context=self.context, initializer=_start_worker,
                                            initargs=(os.getpid(), initializer, initargs))

    def submit(self, fn: Callable, *args: Any) -> cf.Future:
        # The pool starts its processes inside submit.
        with signals_held(), _one_thread_per_worker():
            return self._pool.submit(fn, *args)

    def terminate(self) -> None:
        """Stop every worker now, running tasks included, and drop the queued ones."""
        processes = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for p in processes:
            if p.is_alive():
                p.terminate()
        for p in processes:
            p.join(5)
            if p.is_alive():
                p.kill()
        # The pool's manager thread closes its wake-up pipe as it winds down; if that is still
        # under way at interpreter exit, concurrent.futures' atexit hook writes to the closed pipe
        # and prints a traceback (CPython 3.11). Let it finish here.
        manager = getattr(self._pool, "_executor_manager_thread", None)
        if manager is not None and manager is not threading.current_thread():
            manager.join(5)

    def __enter__(self) -> "WorkerPool":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self._pool.shutdown(wait=True)
        else:
            self.terminate()


@contextlib.contextmanager
def _one_thread_per_worker() -> Iterator[None]:
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k, v in saved.items() if v is None})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)


#: After SIGTERM or Ctrl-C, the command's own clean-up (pools torn down, partial files removed)
#: gets this long; then the process ends whatever still runs: a thread blocked in a read that
#: never returns (a FIFO, a hung mount) or an interrupt swallowed where Python ignores exceptions
#: (a ``__del__``) must not keep it alive until a SIGKILL.
EXIT_GRACE_S = 10.0
#: Once the command has ended, the interpreter's exit handlers (thread joins, atexit) get this long.
EXIT_HANDLERS_S = 3.0
_EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}


class _Deadline:
    """Ends the process at a deadline with the signal's exit status, unless it ends first."""

    def __init__(self) -> None:
        self.code: int | None = None  # the exit status of the first signal; None before one
        self.said = False  # whether the one line saying so was printed
        self.at = 0.0
        self._thread: threading.Thread | None = None

    def arm(self, code: int, seconds: float) -> None:
        self.code = self.code or code
        self.at = time.monotonic() + seconds
        if self._thread is None:
            self._thread = threading.Thread(target=self._wait, daemon=True, name="exit-deadline")
            self._thread.start()

    def _wait(self) -> None:
        while (left := self.at - time.monotonic()) > 0:
            time.sleep(min(left, 0.1))
        self.end_now()

    def end_now(self) -> None:
        if not self.said:
            os.write(2, f"error: {'terminated' if self.code == 143 else 'interrupted'}\n".encode())
        os._exit(self.code or 1)


_deadline = _Deadline()


def signal_exit_code() -> int | None:
    """130 (SIGINT) or 143 (SIGTERM) once one arrived within ``terminated_as_interrupt``; else None."""
    return _deadline.code


@contextlib.contextmanager
def terminated_as_interrupt() -> Iterator[None]:
    """Within: SIGTERM raises ``Terminated`` in the main thread, so the same clean-up as for Ctrl-C
    runs (pools torn down, partial files removed) before the process exits. Either signal also
    sets a deadline (``EXIT_GRACE_S``) after which the process ends regardless, and a second one
    ends it at once. After a signal the handlers stay: the process is on its way out
    (``ending_on_signal``)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_signal(signum, frame):
        if _deadline.code is not None:  # asked twice: the clean-up is not waited for
            _deadline.end_now()
        _deadline.arm(_EXIT_CODES[signum], EXIT_GRACE_S)
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    # A SIGINT that is ignored (a shell's background job) stays ignored.
    ours = [signal.SIGTERM] + ([signal.SIGINT] if signal.getsignal(signal.SIGINT) is signal.default_int_handler else [])
    old = {sig: signal.signal(sig, on_signal) for sig in ours}
    try:
        yield
    finally:
        if _deadline.code is None:
            for sig, handler in old.items():
                signal.signal(sig, handler)


def ending_on_signal(say: Callable[[str], None] | None) -> int:
    """The process exits on the signal that arrived (``signal_exit_code``): returns its exit
    status, after ``say`` printed the one line that says so ('terminated' or 'interrupted' its
    argument; None: the command printed it). From here a further SIGINT or SIGTERM ends the
    process at once, and the interpreter's exit handlers get ``EXIT_HANDLERS_S``."""
    code = _deadline.code
    if code is None:
        raise RuntimeError("no signal arrived")
    for sig in _EXIT_CODES:
        signal.signal(sig, lambda signum, frame: _deadline.end_now())
    _deadline.arm(code, EXIT_HANDLERS_S)
    if say is not None:
        say("terminated" if code == 143 else "interrupted")
    _deadline.said = True
    return code


class Terminated(KeyboardInterrupt):
    """SIGTERM, handled where Ctrl-C is (it is a KeyboardInterrupt)."""


def _start_worker(parent: int, initializer: Callable | None, initargs: tuple) -> None:
    threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True, name="parent-watch").start()
    if initializer is not None:
        initializer(*initargs)


def _exit_when_orphaned(parent: int) -> None:
    # A dead parent's children are re-parented (to init or a subreaper): the ppid changes.
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(1)
