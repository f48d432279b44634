"""Worker processes that do not outlive the process that started them."""

from __future__ import annotations

import contextlib
import ctypes
import importlib
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from types import ModuleType

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def die_with_parent(parent_pid: int) -> None:
    """Have Linux SIGKILL this process when its parent dies (``prctl(PR_SET_PDEATHSIG)``).

    A SIGKILLed parent cannot stop its pool, so its workers would keep running and writing. Neither
    ``multiprocessing`` nor the standard library offer this, hence ctypes. Call it first thing in a
    worker; ``parent_pid`` closes the race of a parent that died before the call. No-op elsewhere.
    """
    if sys.platform != "linux":
        return
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent_pid:
        os._exit(1)


def _start_worker(parent_pid: int) -> None:
    die_with_parent(parent_pid)
    # Ctrl-C reaches the whole process group: a worker then ends silently (the parent reports the interruption
    # in one line) instead of printing a KeyboardInterrupt traceback from wherever it was. A Ctrl-C during the
    # worker's start-up was held back by the mask it inherited (WorkerPool.submit) and ends it here.
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    import torch

    # Tiny tensors: one intra-op thread per worker, the workers themselves use the cores (measured on the fits:
    # 23 ms/iteration with 1 thread, 35 with 2; on a loaded machine two spinning threads made one process ten
    # times slower).
    torch.set_num_threads(1)


class WorkerPool(ProcessPoolExecutor):
    """Worker processes of one intra-op thread each, that die with their parent and stop quietly on Ctrl-C."""

    def __init__(self, workers: int, start_method: str):
        super().__init__(workers, mp_context=multiprocessing.get_context(start_method),
                         initializer=_start_worker, initargs=(os.getpid(),))

    def submit(self, fn: Callable, /, *args, **kwargs) -> Future:
        # Workers are started inside submit and inherit this thread's signal mask (across exec too): with SIGINT
        # blocked, a Ctrl-C during their seconds of start-up waits for _start_worker instead of interrupting an
        # import with a traceback. The parent's own pending Ctrl-C is raised as soon as the mask is restored.
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return super().submit(fn, *args, **kwargs)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def stop_like_ctrl_c(signum: int, frame) -> None:
    """A SIGTERM handler: stop as Ctrl-C does, this process with a KeyboardInterrupt (which the entry point reports
    in its one line), its worker processes at once and without a word. Ctrl-C ends them by SIGINT at its default
    action (``_start_worker``); here they are sent SIGKILL, as abrupt, which also comes ahead of the SIGTERM the pool
    sends the others once one worker is gone."""
    for child in multiprocessing.active_children():
        if child.pid is not None:
            os.kill(child.pid, signal.SIGKILL)
    raise KeyboardInterrupt


@contextlib.contextmanager
def sigterm_at_its_default() -> Iterator[None]:
    """SIGTERM at its default action in the block (the main thread only can set it): Lightning's fit adds the handler
    it finds to its own, which would then stop in the middle of a step instead of after it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def import_keeping_sigterm(name: str) -> ModuleType:
    """``importlib.import_module(name)`` with this process's SIGTERM handler kept: pycolmap's glog installs its own
    at import, which prints a stack trace and kills the process instead of letting it stop in one line."""
    if threading.current_thread() is not threading.main_thread():
        return importlib.import_module(name)
    handler = signal.getsignal(signal.SIGTERM)
    module = importlib.import_module(name)
    signal.signal(signal.SIGTERM, handler)
    return module


def _quiet_broken_worker_connections(previous: Callable) -> Callable:
    """``previous`` (a ``sys.excepthook``) less the traceback of a connection that a worker broke, which the resource
    sharer's thread prints (``multiprocessing.resource_sharer``: it hands a worker the file descriptors of the
    tensors it is sent). A worker stopped by Ctrl-C in the middle of that handshake resets it; a worker that dies
    otherwise is reported by the pool itself (BrokenProcessPool). The main thread's errors are untouched."""

    def hook(kind, value, traceback) -> None:
        in_a_thread = threading.current_thread() is not threading.main_thread()
        if not (issubclass(kind, (ConnectionError, EOFError)) and in_a_thread):
            previous(kind, value, traceback)

    return hook


@contextlib.contextmanager
def stops_quietly(tracebacks: bool = False) -> Iterator[None]:
    """In the block, SIGTERM stops the process as Ctrl-C does (:func:`stop_like_ctrl_c`) and, unless
    ``tracebacks``, a worker's broken connection prints nothing. Both are kept when a KeyboardInterrupt leaves the
    block (the process is stopping: its workers' connections break until it has ended), else put back."""
    hook, term = sys.excepthook, signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, stop_like_ctrl_c)
    if not tracebacks:
        sys.excepthook = _quiet_broken_worker_connections(hook)
    try:
        yield
    except KeyboardInterrupt:
        raise
    except BaseException:
        sys.excepthook = hook
        signal.signal(signal.SIGTERM, term)
        raise
    sys.excepthook = hook
    signal.signal(signal.SIGTERM, term)


def run_units(pool: Executor | None, function: Callable, arguments: Iterable[tuple]) -> Iterator:
    """``function(*args)`` for each tuple, results in order. With a pool every unit is submitted now, before
    the first result is read (so work submitted next queues behind it); without one each runs when read."""
    if pool is None:
        return (function(*args) for args in arguments)
    futures = [pool.submit(function, *args) for args in arguments]
    return (future.result() for future in futures)  # result() re-raises a worker's error here
