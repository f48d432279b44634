"""Worker processes that do not outlive the process that started them."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor

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


def run_units(pool: Executor | None, function: Callable, arguments: Iterable[tuple]) -> Iterator:
    """``function(*args)`` for each tuple, results in order. With a pool every unit is submitted now, before
    the first result is read (so work submitted next queues behind it); without one each runs when read."""
    if pool is None:
        return (function(*args) for args in arguments)
    futures = [pool.submit(function, *args) for args in arguments]
    return (future.result() for future in futures)  # result() re-raises a worker's error here
