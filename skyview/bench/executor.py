"""The one executor of the benches and sweeps: tasks on Dask (a LocalCluster on this machine, or a cluster
at an address) or in this process, each result handed back as it completes."""

from __future__ import annotations

from typing import Callable, Iterable

from skyview.core.errors import SkyviewError

INLINE = "inline"  # scheduler: run the tasks in this process, in order


def run_tasks(fn: Callable, args: Iterable[tuple], *, scheduler: str | None = None, n_workers: int = 2,
              processes: bool = True, on_result: Callable | None = None, on_error: Callable | None = None) -> None:
    """The engine: fn(*a) for every a in args, on Dask (a LocalCluster of n_workers when scheduler is
    None, the cluster at `scheduler` otherwise) or in this process (scheduler="inline");
    on_result(a, result) in this process as each completes (any order); on_error(a, exception) for a
    task that failed on Dask (its worker lost more often than Dask retries it: KilledWorker), when given
    (else the exception is raised). Ctrl-C stops a LocalCluster's workers before it is raised. Shared by
    the coverage sweep and the benches (`skyview bench --jobs`, `--scheduler`)."""
    args = list(args)
    if not args:
        return
    if scheduler == INLINE:
        for a in args:
            r = fn(*a)
            if on_result:
                on_result(a, r)
        return
    import dask
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    try:
        if scheduler is None:
            where = {"host": "127.0.0.1"} if processes else {}  # thread workers talk in-process
            # no statistical profiler in the workers: it samples every task's stack 100 times a second,
            # a third of the time of the benches' Python-heavy trials; and the event loop's health tick
            # (every 20 ms) and the dashboard's system monitor (every 0.5 s), which no one reads here,
            # seldom: each wakes a worker's loop thread, which takes the GIL from its task (the coverage
            # sweep: ~1.5 % of each core; the memory monitor, which enforces the memory limit, is kept)
            with dask.config.set({"distributed.worker.profile.enabled": False,
                                  "distributed.admin.tick.interval": "1s",
                                  "distributed.admin.system-monitor.interval": "5s",
                                  "distributed.nanny.pre-spawn-environ": {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1,
                                                                          "OPENBLAS_NUM_THREADS": 1}}):
                cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=processes,
                                       dashboard_address=None, **where)
            client = Client(cluster)
        else:
            try:
                client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError) as exc:
                raise SkyviewError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        with client:
            futures = {client.submit(fn, *a, pure=False): a for a in args}
            for fut in as_completed(futures):
                try:
                    r = fut.result()
                except Exception as exc:  # noqa: BLE001 - handed to on_error when the caller takes them
                    if on_error is None:
                        raise
                    on_error(futures[fut], exc)
                    continue
                if on_result:
                    on_result(futures[fut], r)
    finally:
        if cluster is not None:
            cluster.close()
