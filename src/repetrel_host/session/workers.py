"""Work that reads a whole file (a check, an analysis, a job's planned time) runs in worker
processes, the server's and hyrel-send's alike.

A thread is not enough: it shares the interpreter's lock with the event loop, and a thread
busy for minutes with a big file makes the loop wait for that lock at each of its wake-ups,
so every printer's stream slows down (measured with ``bench/loop_delay.py``: a streaming
printer at 65 lines/s instead of 200 while a 1 GB file was checked in a thread). The
calling thread waits for the worker; the event loop never does.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
import time
import weakref
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import TypeVar

from repetrel_host.errors import JobError

T = TypeVar("T")

WORKERS = 4  # at once: a small upload's check does not wait behind a big file's
WORKER_NICENESS = 10  # added to the host's: its workers run when it has nothing to do
ORPHAN_CHECK = 1.0  # seconds between a worker's looks at whether its host still runs

_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_given_up: weakref.WeakSet[ProcessPoolExecutor] = weakref.WeakSet()  # by stop_workers


def in_worker(function: Callable[..., T], *args: object, **kwargs: object) -> T:
    """``function(*args, **kwargs)`` in a worker process (any thread but the event loop's:
    this one waits). Its exceptions come back as they were raised. Workers that died (killed,
    out of memory) are replaced and the work tried once more; a second death is a
    :class:`JobError`."""
    for _ in range(2):
        pool = _pool_now()
        try:
            return pool.submit(function, *args, **kwargs).result()
        except BrokenProcessPool:
            if pool in _given_up:
                raise JobError("the work was given up: the host is ending") from None
            _drop(pool)
    raise JobError("the process reading the file ended before it was done")


def _pool_now() -> ProcessPoolExecutor:
    global _pool
    with _lock:
        if _pool is None:
            _pool = ProcessPoolExecutor(
                WORKERS,
                # Not fork: the host has threads, and a forked child inherits their locks.
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_start_worker,
                initargs=(os.getpid(),),
            )
        return _pool


def _drop(pool: ProcessPoolExecutor) -> None:
    global _pool
    with _lock:
        if _pool is pool:
            _pool = None
    pool.shutdown(wait=False, cancel_futures=True)


def stop_workers() -> None:
    """End the workers (the host's shutdown): work under way is given up (its caller gets
    a :class:`JobError`), its process ended now rather than awaited, which would hold the
    host's exit until a big file's work is done."""
    pool = _pool
    if pool is not None:
        _given_up.add(pool)
        processes = list(getattr(pool, "_processes", None) or {})  # Python 3.14 has a way
        _drop(pool)
        for process in processes:
            with contextlib.suppress(ProcessLookupError):
                os.kill(process, signal.SIGTERM)


def _start_worker(host_pid: int) -> None:
    # Ctrl-C in a terminal reaches the whole process group: the host stops its own work,
    # and a worker would only print a traceback.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # Reading a file can wait; a printer's stream cannot: on a board with few cores the
    # host's process comes first.
    os.nice(WORKER_NICENESS)
    # A worker busy with a big file outlives a host that ended (SIGTERM, kill -9) by
    # at most a second.
    threading.Thread(target=_end_with, args=(host_pid,), daemon=True).start()


def _end_with(host_pid: int) -> None:
    while os.getppid() == host_pid:
        time.sleep(ORPHAN_CHECK)
    os._exit(0)
