"""Where frame shards run: a local process pool or a Ray cluster, both calling
:func:`~robustbench3d.runner.shards.run_shard`.

* :class:`LocalExecutor`: ``jobs`` worker processes (``spawn`` context; one intra-op thread each),
  created on first use and kept for the whole run, so each worker creates a victim once and reuses
  it for every later shard. A worker that dies (killed, out of memory) breaks the pool: a new pool
  is started and the unfinished shards are submitted again (up to ``retries`` times).
* :class:`RayExecutor`: one Ray task per shard (``num_cpus=1``, ``max_retries``: Ray reruns the
  shard of a worker that died). ``ray.init(address=...)`` joins a running cluster, without an
  address (or with ``local``) a local one with ``jobs`` CPUs is started (and shut down at the end).
  The address is checked when the executor is made, before any work (:func:`check_ray_address`): its
  form, then a TCP connection to its host and port within :data:`PROBE_TIMEOUT_S` (Ray itself retries
  an unreachable address for many minutes).

Both are started lazily (a run whose cells are all reused starts nothing) and yield results as
shards finish. Shards are idempotent (same files, same bytes), so a shard run twice counts once:
the runner keeps one result per shard.
"""

from __future__ import annotations

import re
import socket
from collections.abc import Iterator, Sequence
from typing import Any

from robustbench3d.errors import RobustBenchError
from robustbench3d.runner.shards import SHARD_FRAMES, Shard, ShardResult, run_shard, worker_setup

EXECUTORS = ("local", "ray")
#: Seconds the TCP check of a Ray address waits for its host to answer: a reachable head answers in
#: milliseconds even across a data centre; a host that does not answer in 5 s is down or filtered.
PROBE_TIMEOUT_S = 5.0
#: HOST:PORT with a host name, an IPv4 address or a bracketed IPv6 address (after an optional ray://).
_ADDRESS = re.compile(r"(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9._-]*[A-Za-z0-9])?):(?P<port>[0-9]{1,5})")
_ADDRESS_FORMS = "HOST:PORT (port 1..65535), ray://HOST:PORT, auto or local"


def _host_port(address: str, text: str) -> tuple[str, int]:
    """``(host, port)`` of ``text`` (HOST:PORT) given as ``--address address``; refuses any other form."""
    match = _ADDRESS.fullmatch(text)
    port = int(match["port"]) if match else 0
    if match is None or not 1 <= port <= 65535:
        raise RobustBenchError(f"--address {address!r}: expected {_ADDRESS_FORMS}")
    return match["host"].strip("[]"), port


def _probe(address: str, host: str, port: int, timeout_s: float) -> None:
    """Open and close a TCP connection to ``host:port`` within ``timeout_s`` seconds, or refuse ``address``."""
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except socket.gaierror as exc:
        raise RobustBenchError(f"--address {address}: unknown host {host!r} ({exc.strerror})") from None
    except ConnectionRefusedError:
        raise RobustBenchError(f"--address {address}: connection refused, nothing listens on port {port} of {host} "
                               "(is the Ray head running? `ray start --head`, docs/executors.md)") from None
    except TimeoutError:
        raise RobustBenchError(f"--address {address}: {host} did not answer on port {port} within {timeout_s:g} s "
                               "(down, or a firewall drops the connection)") from None
    except OSError as exc:
        raise RobustBenchError(f"--address {address}: cannot connect to {host} port {port} "
                               f"({exc.strerror or exc})") from None


def check_ray_address(address: str | None, timeout_s: float = PROBE_TIMEOUT_S) -> str | None:
    """The ``--address`` of ``--executor ray`` checked before any work: the address to give ``ray.init``, or
    None to start a local cluster (no address, or ``local``). ``HOST:PORT`` and ``ray://HOST:PORT`` must accept
    a TCP connection within ``timeout_s`` seconds; ``auto`` must name a cluster Ray recorded on this machine
    (``ray start``, or ``RAY_ADDRESS``), which is then checked the same way. Raises :class:`RobustBenchError`."""
    if address is None or address == "local":
        return None
    if address == "auto":
        _probe(address, *_host_port(address, _auto_address()), timeout_s)
        return address
    _probe(address, *_host_port(address, address.removeprefix("ray://")), timeout_s)
    return address


def _auto_address() -> str:
    """HOST:PORT of the cluster ``ray.init(address="auto")`` would join (Ray's own lookup)."""
    from ray._private.services import canonicalize_bootstrap_address

    try:
        found = canonicalize_bootstrap_address("auto")
    except (ConnectionError, ValueError) as exc:
        raise RobustBenchError(f"--address auto: {exc}") from None
    if found is None:
        raise RobustBenchError("--address auto: no running Ray cluster found on this machine")
    return found


class Executor:
    """Runs shards somewhere; a context manager that releases its workers on exit."""

    kind = "?"

    def __init__(self, jobs: int, shard_frames: int = SHARD_FRAMES):
        from robustbench3d.ranges import PROCESSES_RANGE, check_range

        check_range("--jobs", jobs, *PROCESSES_RANGE, "worker processes")
        if shard_frames < 1:
            raise RobustBenchError(f"shard_frames must be at least 1, got {shard_frames}")
        self.jobs, self.shard_frames = jobs, shard_frames

    def run(self, shards: Sequence[Shard]) -> Iterator[ShardResult]:
        """Each shard's result, in the order they finish."""
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        """JSON record for the cells' provenance."""
        return {"kind": self.kind, "jobs": self.jobs, "shard_frames": self.shard_frames}

    def close(self) -> None:
        """Release the workers."""

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LocalExecutor(Executor):
    """A pool of ``jobs`` local worker processes (see the module doc)."""

    kind = "local"

    def __init__(self, jobs: int, shard_frames: int = SHARD_FRAMES, retries: int = 2, context: str = "spawn"):
        super().__init__(jobs, shard_frames)
        self.retries, self.context = retries, context
        self._pool: Any = None
        self._size = 0

    def _start(self, size: int) -> Any:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        if self._pool is None or self._size < size:
            self.close()
            self._pool = ProcessPoolExecutor(max_workers=size, mp_context=multiprocessing.get_context(self.context),
                                             initializer=worker_setup)
            self._size = size
        return self._pool

    def run(self, shards: Sequence[Shard]) -> Iterator[ShardResult]:
        from concurrent.futures import FIRST_COMPLETED, wait
        from concurrent.futures.process import BrokenProcessPool

        todo = list(shards)
        restarts = 0
        while todo:
            pool = self._start(min(self.jobs, len(todo)))
            futures = {pool.submit(run_shard, shard): shard for shard in todo}
            done_ids: set[int] = set()
            broken: BaseException | None = None
            pending = set(futures)
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    try:
                        result = future.result()
                    except BrokenProcessPool as exc:
                        broken = exc
                        continue
                    done_ids.add(id(futures[future]))
                    yield result
            todo = [shard for shard in todo if id(shard) not in done_ids]
            if broken is None:
                break
            self.close()  # a worker died: a fresh pool for the shards left
            restarts += 1
            if restarts > self.retries:
                raise RobustBenchError(f"local executor: a worker process died {restarts} times; "
                                       f"{len(todo)} shard(s) unfinished ({broken})")

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool, self._size = None, 0


class RayExecutor(Executor):
    """Shards as Ray tasks with retries (see the module doc)."""

    kind = "ray"

    def __init__(self, jobs: int, address: str | None = None, shard_frames: int = SHARD_FRAMES,
                 max_retries: int = 3):
        super().__init__(jobs, shard_frames)
        self.max_retries = max_retries
        self._started_here = False
        self._task: Any = None
        try:
            import ray  # noqa: F401
        except ImportError:
            raise RobustBenchError("--executor ray needs Ray: pip install -c constraints.txt -e '.[ray]'") from None
        self.address = check_ray_address(address)

    def _start(self) -> Any:
        import ray

        if not ray.is_initialized():
            env = {"env_vars": {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}}
            try:
                if self.address:
                    ray.init(address=self.address, runtime_env=env, logging_level="WARNING", log_to_driver=False)
                else:  # "local": a new cluster even where `ray start` left one running
                    ray.init(address="local", num_cpus=self.jobs, runtime_env=env, include_dashboard=False,
                             logging_level="WARNING", log_to_driver=False, object_store_memory=100 * 1024 * 1024)
            except (ConnectionError, TimeoutError, RuntimeError, ValueError) as exc:
                where = f"--address {self.address}" if self.address else "--executor ray"
                first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                raise RobustBenchError(f"{where}: Ray could not start or join the cluster "
                                       f"({type(exc).__name__}: {first})") from None
            self._started_here = True
        if self._task is None:
            self._task = ray.remote(num_cpus=1, max_retries=self.max_retries)(run_shard)
        return ray

    def run(self, shards: Sequence[Shard]) -> Iterator[ShardResult]:
        ray = self._start()
        pending = [self._task.remote(shard) for shard in shards]
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "address": self.address, "max_retries": self.max_retries}

    def close(self) -> None:
        if self._started_here:
            import ray

            ray.shutdown()
            self._started_here, self._task = False, None


def make_executor(kind: str, jobs: int | None = None, address: str | None = None) -> Executor | None:
    """The executor of ``run --executor KIND --jobs J [--address ADDR]``; None for the one-process path
    (``local`` with one job). ``jobs`` defaults to the CPU count."""
    if kind not in EXECUTORS:
        raise RobustBenchError(f"--executor: unknown executor {kind!r}; choose from {', '.join(EXECUTORS)}")
    from robustbench3d.ranges import PROCESSES_RANGE, check_range, default_processes

    jobs = default_processes() if jobs is None else jobs
    check_range("--jobs", jobs, *PROCESSES_RANGE, "worker processes")
    if address is not None and kind != "ray":
        raise RobustBenchError("--address joins a Ray cluster: give it with --executor ray")
    if kind == "ray":
        return RayExecutor(jobs, address)
    return LocalExecutor(jobs) if jobs > 1 else None


__all__ = ["EXECUTORS", "PROBE_TIMEOUT_S", "Executor", "LocalExecutor", "RayExecutor", "check_ray_address",
           "make_executor"]
