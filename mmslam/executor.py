"""Where parallel work runs: a local process pool or a Dask cluster, behind one small interface.

Used by ``mmslam ablate`` (one filter job per task) and ``mmslam trace --executor dask`` (one chunk
of steps per task); both check their options with :func:`check_executor` before any work, so a bad
``--scheduler`` or ``--workers`` is one line and exit 2 at once, and both open a :class:`Pool` with
:func:`open_pool` / :func:`dask_pool`.

``local``: a ``concurrent.futures`` process pool (``spawn`` context, BLAS/OpenMP threads pinned to
1). ``dask``: a ``dask.distributed`` scheduler at an address (checked by :func:`check_dask_address`,
reached within :data:`CONNECT_TIMEOUT_S`), or a ``LocalCluster`` started here (processes, one thread
each) when no address is given. Workers of a remote scheduler must see the output folder at the same
path (shared file system) and have mmslam installed.

Signals: Ctrl-C belongs to the parent process, which keeps what is finished and stops the workers.
Worker processes are started with SIGINT blocked (the mask is inherited through ``fork`` and
``exec``), so a Ctrl-C sent to the whole process group by a terminal never reaches a worker's Python,
not even during its start-up imports; a signal arriving while a worker is being started is handled
once the start is complete (:func:`~mmslam.errors.deferred_sigint`), so the pool is never left half
made. Aborting a local pool (:meth:`Pool.cancel`) terminates its processes and waits a bounded time.

This module sits at the bottom of the package (it imports only :mod:`mmslam.errors` and
:mod:`mmslam.limits`; ``distributed`` is imported when a Dask pool is opened).
"""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from typing import Any

from mmslam.errors import ConfigError, MmslamError, deferred_sigint
from mmslam.limits import MAX_WORKERS

EXECUTORS: tuple[str, ...] = ("local", "dask")
"""Executor names (``--executor``)."""
DASK_SCHEMES: tuple[str, ...] = ("tcp", "tls", "ws", "wss", "ucx")
"""Address schemes a Dask scheduler address may name."""
CONNECT_TIMEOUT_S = 3.0
"""How long to wait for a dask scheduler before giving up (seconds)."""
ABORT_WAIT_S = 5.0
"""How long an aborted local pool waits for each terminated process / its manager thread (seconds)."""

THREAD_VARS: tuple[str, ...] = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                "NUMEXPR_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "BLIS_NUM_THREADS")
"""Thread-count variables of the BLAS / OpenMP libraries, set to 1 in every worker."""

_DASK_MISSING = ("--executor dask needs dask.distributed; install it with `pip install 'mmslam[dask]'` or use "
                 "--executor local")


def one_line(e: BaseException) -> str:
    """An exception's message on one line, at most 200 characters (its type name if it has none)."""
    msg = " ".join(str(e).split()) or type(e).__name__
    return msg if len(msg) <= 200 else msg[:197] + "..."


# ====================================================================== option checks
def check_dask_address(scheduler: str) -> str:
    """``scheduler`` if it reads ``[scheme://]host:port`` (port 1..65535); one-line :class:`ConfigError` otherwise.

    Checked before a ``Client`` is made: a malformed address would otherwise hang for the
    connect timeout and print a ``Client.__del__`` traceback.
    """
    import re

    m = re.fullmatch(r"(?:([a-z]+)://)?(\[[0-9a-fA-F:]+\]|[A-Za-z0-9._-]+):(\d{1,5})", scheduler.strip())
    if m is None or (m.group(1) is not None and m.group(1) not in DASK_SCHEMES) or not 1 <= int(m.group(3)) <= 65535:
        raise ConfigError(f"--scheduler {scheduler!r}: expected an address like tcp://host:8786 (scheme one of "
                          f"{', '.join(DASK_SCHEMES)}, port 1..65535)")
    return scheduler.strip()


def check_executor(executor: str, scheduler: str | None, workers: int | None) -> None:
    """Reject bad ``--executor`` / ``--scheduler`` / ``--workers`` values with a one-line :class:`ConfigError`.

    ``--scheduler`` needs ``--executor dask`` and a well-formed address; ``--workers`` is 1..:data:`MAX_WORKERS`.
    No connection is attempted (that happens when the pool opens).
    """
    if executor not in EXECUTORS:
        raise ConfigError(f"--executor {executor}: expected one of {', '.join(EXECUTORS)}")
    if scheduler and executor != "dask":
        raise ConfigError("--scheduler is only used with --executor dask; add --executor dask or drop it")
    if scheduler:
        check_dask_address(scheduler)
    if workers is not None and not 1 <= int(workers) <= MAX_WORKERS:
        raise ConfigError(f"--workers {workers}: expected 1..{MAX_WORKERS} workers")


def pool_size(workers: int | None, n_tasks: int) -> int:
    """Processes to start: ``workers`` (default: the CPU count), never more than the tasks, at least 1."""
    return max(1, min(int(workers or os.cpu_count() or 1), int(n_tasks)))


# ====================================================================== worker processes
@contextlib.contextmanager
def single_thread_env() -> Iterator[None]:
    """Set the BLAS/OpenMP thread variables to 1 while worker processes are started."""
    old = {k: os.environ.get(k) for k in THREAD_VARS}
    os.environ.update({k: "1" for k in THREAD_VARS})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def starting_workers() -> Iterator[None]:
    """Around code that starts worker processes: they start with SIGINT blocked, and a Ctrl-C / SIGTERM
    to this process is handled when the block ends (not half-way through a process start).

    The signal mask of the starting thread is inherited through ``fork`` and ``exec``, so the worker's
    interpreter never sees a Ctrl-C sent to the process group (it stays pending, blocked, for the life
    of the worker); threads started in the block (e.g. Dask's event loop, which starts the nanny
    workers) inherit it too. Does nothing to the mask outside the main thread.
    """
    import signal
    import threading

    with deferred_sigint():
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def worker_init(parent_pid: int) -> None:
    """Local-pool worker start-up: one BLAS thread, Ctrl-C ignored, and exit when the parent process is gone.

    A ``kill -9`` of the parent would otherwise leave the spawned workers blocked forever on
    their task queue (they hold its write end too, so they never see EOF).
    """
    import signal
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it saves, then stops us
    for k in THREAD_VARS:
        os.environ[k] = "1"

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="mmslam-parent-watch", daemon=True).start()


# ====================================================================== pools
class Pool:
    """Uniform submit / as_completed / cancel over concurrent.futures and dask.distributed.

    ``submit(fn, *args, key=None)`` returns a future (``key``: a readable task name for Dask's
    dashboard and logs, unique per task); ``as_completed(futures)`` yields them as they finish;
    ``cancel(futures)`` stops everything not finished (a local pool: its processes are terminated,
    finished results stay readable); ``n_workers`` and ``describe`` say what runs the tasks.
    """

    def __init__(self, submit: Callable[..., Any], as_completed: Callable[[list], Iterator[Any]],
                 cancel: Callable[[list], None], n_workers: int, describe: str) -> None:
        self.submit = submit
        self.as_completed = as_completed
        self.cancel = cancel
        self.n_workers = n_workers
        self.describe = describe


def _abort_local(ex: Any) -> None:
    """Stop a ``ProcessPoolExecutor`` now: drop queued tasks, terminate its processes, wait a bounded time.

    Queued futures are cancelled by the executor's own manager thread (``cancel_futures``), never from
    here: cancelling them from this thread races with the manager thread marking them failed once
    the processes are gone (``InvalidStateError`` tracebacks). The manager thread is then joined
    for at most :data:`ABORT_WAIT_S`; if it is stuck, it is removed from the interpreter's exit
    join so that the process still exits.
    """
    import concurrent.futures.process as cfp

    procs = list((getattr(ex, "_processes", None) or {}).values())  # shutdown() forgets them
    thread = getattr(ex, "_executor_manager_thread", None)
    ex.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.terminate()  # in-flight tasks: cancelled now (they re-run on resume), not awaited
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.join(ABORT_WAIT_S)
            if proc.is_alive():
                proc.kill()
                proc.join(ABORT_WAIT_S)
    if thread is not None:
        thread.join(ABORT_WAIT_S)
        if thread.is_alive():
            getattr(cfp, "_threads_wakeups", {}).pop(thread, None)


@contextlib.contextmanager
def local_pool(workers: int | None, n_tasks: int) -> Iterator[Pool]:
    """A process pool of :func:`pool_size` processes (``spawn``, one BLAS thread each) for ``n_tasks`` tasks.

    On an exception (Ctrl-C included) the pool is aborted (:func:`_abort_local`), else shut down
    after its tasks.
    """
    import concurrent.futures as cf
    import multiprocessing as mp

    n = pool_size(workers, n_tasks)
    with single_thread_env():
        ex = cf.ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn"),
                                    initializer=worker_init, initargs=(os.getpid(),))
        aborted: list[bool] = []

        def submit(fn: Callable[..., Any], *args: Any, key: str | None = None) -> Any:
            with starting_workers():  # submit() starts the worker processes (spawn: one per submit)
                return ex.submit(fn, *args)

        def cancel(futures: list) -> None:
            if not aborted:
                aborted.append(True)
                _abort_local(ex)

        try:
            yield Pool(submit, lambda fs: cf.as_completed(fs), cancel, n, f"local pool, {n} processes")
        except BaseException:
            cancel([])
            raise
        else:
            ex.shutdown(wait=True)


def connect_dask(scheduler: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """A ``dask.distributed.Client`` for ``scheduler``; one-line :class:`MmslamError` if unreachable."""
    check_dask_address(scheduler)
    try:
        from distributed import Client
    except ImportError:
        raise MmslamError(_DASK_MISSING) from None
    import logging

    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    try:
        return Client(scheduler, timeout=f"{timeout_s}s", set_as_default=False)
    except Exception as e:  # OSError / TimeoutError / ValueError for a malformed address
        raise MmslamError(f"cannot reach the dask scheduler at {scheduler} ({one_line(e)}); start it "
                          "(`dask scheduler`) and check the address, or drop --scheduler to start a "
                          "local cluster") from None


def close_client(client: Any) -> None:
    """Close a ``distributed.Client`` within :data:`CONNECT_TIMEOUT_S`, quietly (a lost scheduler cannot be
    told either)."""
    with contextlib.suppress(Exception):
        client.close(timeout=CONNECT_TIMEOUT_S)


@contextlib.contextmanager
def dask_pool(scheduler: str | None, workers: int | None, n_tasks: int, client: Any = None) -> Iterator[Pool]:
    """A :class:`Pool` on ``client``, else on the scheduler at ``scheduler``, else on a ``LocalCluster`` of
    :func:`pool_size` processes with one thread each (started here and closed at the end)."""
    import uuid

    cluster = None
    own = client is None
    if client is not None:
        where = "given client"
    elif scheduler:
        client, where = connect_dask(scheduler), scheduler
    else:
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise MmslamError(_DASK_MISSING) from None
        import logging

        logging.getLogger("distributed").setLevel(logging.CRITICAL)
        n = pool_size(workers, n_tasks)
        with single_thread_env(), starting_workers():
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
            client = Client(cluster, set_as_default=False)
        where = "local cluster"
    try:
        from distributed import as_completed

        n_workers = len(client.scheduler_info().get("workers", {}))
        if n_workers == 0:
            import sys

            print(f"note: the dask scheduler at {scheduler} has no workers yet; tasks wait until workers "
                  "join (`dask worker <address>`)", file=sys.stderr)
        token = uuid.uuid4().hex[:8]

        def submit(fn: Callable[..., Any], *args: Any, key: str | None = None) -> Any:
            return client.submit(fn, *args, pure=False, key=None if key is None else f"mmslam-{key}-{token}")

        yield Pool(submit, lambda fs: as_completed(fs, loop=client.loop), lambda fs: client.cancel(fs), n_workers,
                   f"dask ({where}), {n_workers} workers")
    finally:
        if own:
            close_client(client)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=CONNECT_TIMEOUT_S)


def open_pool(executor: str, scheduler: str | None, workers: int | None, n_tasks: int
              ) -> contextlib.AbstractContextManager[Pool]:
    """``with open_pool("local" | "dask", scheduler, workers, n_tasks) as pool:`` (see :func:`local_pool`,
    :func:`dask_pool`)."""
    check_executor(executor, scheduler, workers)
    return local_pool(workers, n_tasks) if executor == "local" else dask_pool(scheduler, workers, n_tasks)
