"""Where the sweep's trainings run: in this process (one worker), a pool of local worker processes, or Ray tasks.

The runner's :mod:`~robustbench3d.runner.executors` run frame shards of benchmark cells; a training is one long
job instead, so this module runs :func:`~robustbench3d.sweep.train.train_point` jobs on the same two kinds of
worker, set up the same way: ``local`` processes (``spawn``, one intra-op thread each,
:func:`~robustbench3d.runner.shards.worker_setup`) or Ray (``num_cpus=1`` tasks; the cluster address checked up
front by :func:`~robustbench3d.runner.executors.check_ray_address`). Independent points run in parallel up to
``workers``. When a job fails, the jobs already running finish (their objects are kept), no new one starts, and
the first error is raised: a rerun resumes.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

from robustbench3d.sweep.train import TrainJob, train_point


def run_jobs(jobs: Sequence[TrainJob], kind: str = "local", workers: int = 1, address: str | None = None,
             log: Callable[[str], None] | None = None) -> Iterator[dict[str, Any]]:
    """Each job's result (:func:`~robustbench3d.sweep.train.train_point`), in the order they finish."""
    if not jobs:
        return
    if kind == "ray":
        yield from _ray(jobs, workers, address)
    elif workers == 1 or len(jobs) == 1:
        for job in jobs:
            yield train_point(job, log)
    else:
        yield from _processes(jobs, workers)


def _processes(jobs: Sequence[TrainJob], workers: int) -> Iterator[dict[str, Any]]:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    from robustbench3d.runner.shards import worker_setup

    pool = ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn"),
                               initializer=worker_setup)
    error: BaseException | None = None
    try:
        pending = {pool.submit(train_point, job) for job in jobs}
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                if future.cancelled():
                    continue
                exc = future.exception()
                if exc is not None:
                    if error is None:
                        error = exc
                        for other in pending:
                            other.cancel()
                    continue
                yield future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    if error is not None:
        raise error


def _ray(jobs: Sequence[TrainJob], workers: int, address: str | None) -> Iterator[dict[str, Any]]:
    from robustbench3d.errors import RobustBenchError
    from robustbench3d.runner.executors import check_ray_address

    try:
        import ray
    except ImportError:
        raise RobustBenchError("--executor ray needs Ray: pip install -c constraints.txt -e '.[ray]'") from None
    target = check_ray_address(address)
    started = False
    if not ray.is_initialized():
        env = {"env_vars": {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}}
        if target:
            ray.init(address=target, runtime_env=env, logging_level="WARNING", log_to_driver=False)
        else:
            ray.init(address="local", num_cpus=workers, runtime_env=env, include_dashboard=False,
                     logging_level="WARNING", log_to_driver=False)
        started = True
    task = ray.remote(num_cpus=1, max_retries=0)(train_point)
    try:
        pending = [task.remote(job) for job in jobs]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started:
            ray.shutdown()


__all__ = ["run_jobs"]
