"""Execution engines for chunked offline work: the same jobs on local processes or on Ray.

The offline pipeline (collection, sweeps) is a list of independent jobs, each a pure
function of its arguments, run by workers that first build an expensive state (a robot
model with pinocchio/coal objects, which never cross a process boundary). An engine takes
a :class:`Work` — how to build that state and what to do per job, both importable
module-level functions — and yields the jobs' results as they finish, so the caller (the
driver) writes every output file and draws the progress bar. Because workers only compute
and return, the files a run writes do not depend on where the jobs ran: a chunk made on a
remote node of a cluster is the same bytes as one made in a local process.

- :class:`LocalEngine`: this machine's processes (fork), or in-process for one worker; the
  default, needs nothing beyond the standard library.
- :class:`RayEngine`: a Ray cluster — joined with ``address`` (``ray start`` on the
  machines), else a private local instance. One actor per worker slot holds the state;
  Ray retries a job whose worker died, and a job that still fails raises here, after every
  result that did arrive has been handed to the caller (so a resumed run redoes only the
  missing jobs). Ray is imported only when this engine is used.

Waits are bounded: when no job finishes within ``stall_s`` the run stops with an error
instead of hanging on a dead cluster.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Protocol

ENGINES = ("local", "ray")
STALL_S = 900.0
"""Longest wait for the next result before giving up (a 5,000-sample chunk takes ~2 s on a
quiet core; this leaves room for a machine loaded twenty-fold and a slow cluster start)."""


class EngineError(RuntimeError):
    """The engine could not run the jobs (cluster unreachable, nothing finishing)."""


@dataclass(frozen=True)
class Work:
    """What the workers do: ``state = setup(*setup_args)`` once per worker, then
    ``run(state, job)`` per job. Both must be module-level functions (they are sent by
    reference), the arguments and results plain data."""

    setup: Callable[..., Any]
    setup_args: tuple
    run: Callable[[Any, Any], Any]


class Engine(Protocol):
    def map(self, work: Work, jobs: Sequence[Any]) -> Iterator[Any]:
        """Results of ``work.run`` over ``jobs``, in the order they finish."""
        ...


# ---- local processes ------------------------------------------------------------------
_STATE: Any = None


def _init_local(setup: Callable[..., Any], args: tuple) -> None:
    global _STATE
    _STATE = setup(*args)


def _run_local(run: Callable[[Any, Any], Any], job: Any) -> Any:
    return run(_STATE, job)


class LocalEngine:
    """Processes on this machine. The pool forks (Linux), so a plain script needs no
    ``__main__`` guard; each worker builds its own state in its initializer. Where fork is
    missing, spawn is used. A worker that dies raises ``BrokenProcessPool`` instead of
    hanging."""

    def __init__(self, workers: int = 1, stall_s: float = STALL_S) -> None:
        if not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        self.workers, self.stall_s = workers, stall_s

    def map(self, work: Work, jobs: Sequence[Any]) -> Iterator[Any]:
        jobs = list(jobs)
        if not jobs:
            return
        if self.workers == 1 or len(jobs) == 1:
            state = work.setup(*work.setup_args)
            for job in jobs:
                yield work.run(state, job)
            return
        methods = multiprocessing.get_all_start_methods()
        ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
        with ProcessPoolExecutor(min(self.workers, len(jobs)), mp_context=ctx,
                                 initializer=_init_local,
                                 initargs=(work.setup, work.setup_args)) as pool:
            pending = {pool.submit(_run_local, work.run, job) for job in jobs}
            while pending:
                done, pending = wait(pending, timeout=self.stall_s,
                                     return_when=FIRST_COMPLETED)
                if not done:
                    for f in pending:
                        f.cancel()
                    raise EngineError(f"no job finished in {self.stall_s:.0f} s")
                for future in done:
                    yield future.result()


# ---- Ray ------------------------------------------------------------------------------
def _actor_class(ray: Any) -> Any:
    """The worker actor, defined when Ray is first used so that importing this module does
    not import Ray. ``max_restarts``/``max_task_retries``: a worker process that dies is
    restarted and its job run again — safe, as every job is a pure function."""

    @ray.remote(num_cpus=1, max_restarts=2, max_task_retries=2)
    class EngineWorker:
        def __init__(self, setup: Callable[..., Any], args: tuple) -> None:
            self.state = setup(*args)

        def run(self, run: Callable[[Any, Any], Any], job: Any) -> Any:
            return run(self.state, job)

    return EngineWorker


def _local_address(address: str) -> bool:
    return address.rsplit(":", 1)[0] in ("127.0.0.1", "localhost")


class RayEngine:
    """Jobs on a Ray cluster: ``address`` ("host:port" of a ``ray start --head``) joins an
    existing cluster; None starts a private local instance with ``workers`` CPUs (and
    stops it afterwards). ``workers`` caps the actors (default: every CPU of the cluster).
    The code must be importable on every node (the same installation, or a shared
    PYTHONPATH); results travel back to the driver through Ray's object store."""

    def __init__(self, address: str | None = None, workers: int | None = None,
                 stall_s: float = STALL_S, in_flight: int = 2) -> None:
        if workers is not None and (not isinstance(workers, int) or workers < 1):
            raise ValueError(f"workers must be a positive integer, got {workers!r}")
        self.address, self.workers = address, workers
        self.stall_s, self.in_flight = stall_s, in_flight

    def _connect(self, ray: Any) -> bool:
        """Connect (or start); True when this engine started Ray and must shut it down."""
        if ray.is_initialized():
            return False
        options: dict[str, Any] = {"logging_level": "ERROR", "log_to_driver": False,
                                   "include_dashboard": False}
        if self.address:
            if _local_address(self.address):
                options["_node_ip_address"] = "127.0.0.1"
            del options["include_dashboard"]
            try:
                ray.init(address=self.address, **options)
            except (ConnectionError, RuntimeError) as exc:
                raise EngineError(f"cannot join the Ray cluster at {self.address}: {exc}") \
                    from exc
        else:  # "local": a new private instance, never some cluster found on the machine
            ray.init(address="local", num_cpus=self.workers, _node_ip_address="127.0.0.1",
                     **options)
        return True

    def map(self, work: Work, jobs: Sequence[Any]) -> Iterator[Any]:
        jobs = list(jobs)
        if not jobs:
            return
        import ray

        started = self._connect(ray)
        actors: list[Any] = []
        try:
            cpus = int(ray.cluster_resources().get("CPU", 1))
            n = max(1, min(self.workers or cpus, cpus, len(jobs)))
            worker = _actor_class(ray)
            actors = [worker.remote(work.setup, work.setup_args) for _ in range(n)]
            queue = list(reversed(jobs))
            pending: dict[Any, Any] = {}

            def submit(actor: Any) -> None:
                if queue:
                    pending[actor.run.remote(work.run, queue.pop())] = actor

            for actor in actors:
                for _ in range(self.in_flight):
                    submit(actor)
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=self.stall_s)
                if not ready:
                    raise EngineError(f"no job finished in {self.stall_s:.0f} s on the "
                                      "Ray cluster")
                actor = pending.pop(ready[0])
                submit(actor)
                yield ray.get(ready[0])
        finally:
            for actor in actors:
                ray.kill(actor)
            if started:
                ray.shutdown()


def make_engine(name: str = "local", workers: int | None = None,
                address: str | None = None) -> Engine:
    """The engine called ``name`` ("local" or "ray"); ``address`` only applies to Ray."""
    if name == "local":
        if address:
            raise ValueError("--address needs --engine ray")
        return LocalEngine(workers or 1)
    if name == "ray":
        return RayEngine(address, workers)
    raise ValueError(f"unknown engine {name!r}; choose from {', '.join(ENGINES)}")
