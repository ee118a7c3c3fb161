"""Where the ablation's jobs run: a local process pool or a Dask cluster, behind one small interface."""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from typing import Any

from mmslam.errors import ConfigError, MmslamError


CONNECT_TIMEOUT_S = 3.0
"""How long to wait for a dask scheduler before giving up (seconds)."""


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                "VECLIB_MAXIMUM_THREADS", "BLIS_NUM_THREADS")


@contextlib.contextmanager
def _single_thread_env() -> Iterator[None]:
    """Set the BLAS/OpenMP thread variables to 1 while worker processes are started."""
    old = {k: os.environ.get(k) for k in _THREAD_VARS}
    os.environ.update({k: "1" for k in _THREAD_VARS})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _worker_init(parent_pid: int) -> None:
    """Local-pool worker start-up: one BLAS thread, and exit when the parent process is gone.

    A ``kill -9`` of the parent would otherwise leave the spawned workers blocked forever on
    their task queue (they hold its write end too, so they never see EOF).
    """
    import signal
    import threading

    for k in _THREAD_VARS:
        os.environ[k] = "1"
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it saves, then stops us

    def watch() -> None:
        while True:
            time.sleep(0.5)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="mmslam-parent-watch", daemon=True).start()


class _Pool:
    """Uniform submit / as_completed / cancel over concurrent.futures and dask.distributed."""

    def __init__(self, submit: Callable[..., Any], as_completed: Callable[[list], Iterator[Any]],
                 cancel: Callable[[list], None], n_workers: int, describe: str) -> None:
        self.submit = submit
        self.as_completed = as_completed
        self.cancel = cancel
        self.n_workers = n_workers
        self.describe = describe


@contextlib.contextmanager
def _local_pool(workers: int | None, n_jobs: int) -> Iterator[_Pool]:
    import concurrent.futures as cf
    import multiprocessing as mp

    n = max(1, min(int(workers or os.cpu_count() or 1), n_jobs))
    with _single_thread_env():
        ex = cf.ProcessPoolExecutor(max_workers=n, mp_context=mp.get_context("spawn"),
                                    initializer=_worker_init, initargs=(os.getpid(),))
        try:
            yield _Pool(lambda fn, *a: ex.submit(fn, *a), lambda fs: cf.as_completed(fs),
                        lambda fs: [f.cancel() for f in fs], n, f"local pool, {n} processes")
        except BaseException:
            procs = list((getattr(ex, "_processes", None) or {}).values())  # shutdown() forgets them
            ex.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.terminate()  # in-flight jobs: cancelled now (they re-run on resume), not awaited
            raise
        else:
            ex.shutdown(wait=True)


def _one_line(e: BaseException) -> str:
    msg = " ".join(str(e).split()) or type(e).__name__
    return msg if len(msg) <= 200 else msg[:197] + "..."


DASK_SCHEMES: tuple[str, ...] = ("tcp", "tls", "ws", "wss", "ucx")


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


def connect_dask(scheduler: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """A ``dask.distributed.Client`` for ``scheduler``; one-line :class:`MmslamError` if unreachable."""
    check_dask_address(scheduler)
    try:
        from distributed import Client
    except ImportError:
        raise MmslamError("--executor dask needs dask.distributed; install it with "
                          "`pip install 'mmslam[dask]'` or use --executor local") from None
    import logging

    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    try:
        return Client(scheduler, timeout=f"{timeout_s}s", set_as_default=False)
    except Exception as e:  # OSError / TimeoutError / ValueError for a malformed address
        raise MmslamError(f"cannot reach the dask scheduler at {scheduler} ({_one_line(e)}); start it "
                          "(`dask scheduler`) and check the address, or drop --scheduler to start a "
                          "local cluster") from None


@contextlib.contextmanager
def _dask_pool(scheduler: str | None, workers: int | None, n_jobs: int) -> Iterator[_Pool]:
    import uuid

    cluster = None
    if scheduler:
        client = connect_dask(scheduler)
    else:
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise MmslamError("--executor dask needs dask.distributed; install it with "
                              "`pip install 'mmslam[dask]'` or use --executor local") from None
        import logging

        n = max(1, min(int(workers or os.cpu_count() or 1), n_jobs))
        with _single_thread_env():
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
        client = Client(cluster, set_as_default=False)
    try:
        from distributed import as_completed

        n_workers = len(client.scheduler_info().get("workers", {}))
        if n_workers == 0:
            import sys

            print(f"note: the dask scheduler at {scheduler} has no workers yet; jobs wait until workers "
                  "join (`dask worker <address>`)", file=sys.stderr)
        token = uuid.uuid4().hex[:8]
        where = "local cluster" if cluster is not None else scheduler

        def submit(fn: Callable[..., Any], *args: Any) -> Any:
            key = f"mmslam-{args[1]}-seed{args[2]}-{token}"
            return client.submit(fn, *args, pure=False, key=key)

        yield _Pool(submit, lambda fs: as_completed(fs, loop=client.loop), lambda fs: client.cancel(fs), n_workers,
                    f"dask ({where}), {n_workers} workers")
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
