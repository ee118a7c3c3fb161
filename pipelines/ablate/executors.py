"""Where the ablation's jobs run: the shared executor module :mod:`mmslam.executor` (a local process pool or
a Dask cluster), under the names this package has always exported."""
from __future__ import annotations

from mmslam.executor import (CONNECT_TIMEOUT_S, DASK_SCHEMES, THREAD_VARS, Pool, check_dask_address,  # noqa: F401
                             connect_dask, dask_pool, local_pool, one_line, open_pool, single_thread_env,
                             worker_init)

_one_line = one_line
_THREAD_VARS = THREAD_VARS
_Pool = Pool
_single_thread_env = single_thread_env
_worker_init = worker_init
_local_pool = local_pool
_dask_pool = dask_pool
