"""Run jobs beyond this process: local worker processes (spawn) or Ray tasks, with retries.

An executor takes jobs under keys (``submit``) and hands back results one at a time in the
order they finish (``next_result``). A job is a picklable value and the function that runs it
is named as ``"module:function"``, imported in the worker (after the worker's thread limits are
set, before numpy or torch load).

Failures: a job whose worker dies (killed, out of memory, ``os._exit``) or that raises is run
again, up to ``max_attempts`` in all; only that job is lost with its worker, the other workers
keep theirs. Past ``max_attempts`` :class:`JobFailed` names the job and the last error. The job
function must therefore be idempotent: a second attempt must start from scratch.

- :class:`InlineExecutor`: in this process, one job at a time (no isolation: an exception is
  retried, a crash ends the whole run).
- :class:`LocalPool`: ``workers`` long-lived processes of the ``spawn`` context, one pipe each;
  a dead worker is replaced.
- :class:`RayExecutor`: one Ray task per job (``num_cpus=1``), Ray's own retries
  (``max_retries`` for dead workers and nodes, ``retry_exceptions`` for exceptions).

Logs: a local worker logs to stderr in :data:`LOG_FORMAT` (the command lines' format) at the
level this process had when the pool was made, its records marked with its process name.
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing as mp
import os
import traceback
from collections import deque
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol

log = logging.getLogger("beavr_sim.scaling")

#: The one log format of the command lines (``logging.basicConfig(format=LOG_FORMAT)``) and of
#: their local workers.
LOG_FORMAT = "%(levelname)s %(name)s: %(message)s"
#: What a worker puts before :data:`LOG_FORMAT`: which worker logged.
WORKER_LOG_PREFIX = "[%(processName)s] "


def configure_worker_logging(level: int) -> None:
    """A worker's root logger: stderr, :data:`WORKER_LOG_PREFIX` + :data:`LOG_FORMAT`."""
    logging.basicConfig(level=level, format=WORKER_LOG_PREFIX + LOG_FORMAT, force=True)


#: Set in every worker (unless already set there): one thread of BLAS / OpenMP / torch and of
#: Mesa's software rasterizer (llvmpipe) per worker process, as the processes themselves are
#: the parallelism (llvmpipe's default, a thread per core in every worker, oversubscribes).
WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "LP_NUM_THREADS": "1",
}

#: Environment variables forwarded to Ray workers when set here (a cluster's workers do not
#: inherit the driver's environment).
FORWARDED_ENV = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "HF_HUB_OFFLINE", "HF_LEROBOT_HOME")

RAY_MISSING = (
    "--ray needs Ray, which is an optional extra: pip install -e '.[scale]' (or pip install "
    "'ray>=2.9') in this environment and on every node of the cluster"
)


class JobFailed(RuntimeError):
    """A job failed on every attempt."""

    def __init__(self, key: Hashable, attempts: int, error: str):
        super().__init__(f"job {key!r} failed {attempts} time(s); last error:\n{error}")
        self.key = key
        self.attempts = attempts
        self.error = error


@dataclass(frozen=True)
class ScaleConfig:
    """Where jobs run. ``workers``: local worker processes (None: one per core); with ``ray``,
    the most jobs in flight at once (None: the cluster's CPUs). ``ray_address``: an existing
    cluster (``auto``, ``ray://head:10001``, ``head:6379``); None: ``RAY_ADDRESS`` if set, else a
    private local instance for this run."""

    workers: int | None = None
    ray: bool = False
    ray_address: str | None = None
    max_attempts: int = 3

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be >= 1 (or None: one per core), got {self.workers}")
        if self.max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {self.max_attempts}")
        if self.ray_address is not None and not self.ray:
            raise ValueError("ray_address needs ray=True (--ray-address goes with --ray)")

    @property
    def local_workers(self) -> int:
        return self.workers if self.workers is not None else max(1, os.cpu_count() or 1)

    @property
    def in_process(self) -> bool:
        """One local worker: run in this process."""
        return not self.ray and self.local_workers == 1

    @property
    def backend(self) -> str:
        return "ray" if self.ray else "inline" if self.in_process else "local"


def resolve(function: str) -> Callable[[Any], Any]:
    """``"package.module:function"`` -> the function."""
    module, _, name = function.partition(":")
    if not module or not name:
        raise ValueError(f"a job function is named 'module:function', got {function!r}")
    return getattr(importlib.import_module(module), name)


class Executor(Protocol):
    capacity: int
    backend: str

    def submit(self, key: Hashable, job: Any) -> None: ...

    def next_result(self) -> tuple[Hashable, Any]: ...

    def retire_idle(self) -> int:
        """Release the workers that have no job now (no more work is coming for them);
        returns how many. A job submitted later still runs."""
        ...

    @property
    def pending(self) -> int: ...

    def close(self) -> None: ...


class _Retries:
    """Attempt bookkeeping shared by the executors."""

    def __init__(self, max_attempts: int):
        self.max_attempts = max_attempts
        self.attempts: dict[Hashable, int] = {}
        self.retried = 0

    def failed(self, key: Hashable, error: str) -> None:
        """Count a failed attempt; raise :class:`JobFailed` when none is left."""
        self.attempts[key] = self.attempts.get(key, 0) + 1
        if self.attempts[key] >= self.max_attempts:
            raise JobFailed(key, self.attempts[key], error)
        self.retried += 1
        log.warning(
            "job %r failed (attempt %d of %d), running it again: %s",
            key,
            self.attempts[key],
            self.max_attempts,
            error.strip().splitlines()[-1] if error.strip() else "?",
        )


class InlineExecutor:
    """Jobs run in this process when their result is asked for."""

    backend = "inline"

    def __init__(self, function: str, max_attempts: int = 3):
        self._fn = resolve(function)
        self._queue: deque[tuple[Hashable, Any]] = deque()
        self._retries = _Retries(max_attempts)
        self.capacity = 1

    @property
    def pending(self) -> int:
        return len(self._queue)

    @property
    def retried(self) -> int:
        return self._retries.retried

    def submit(self, key: Hashable, job: Any) -> None:
        self._queue.append((key, job))

    def next_result(self) -> tuple[Hashable, Any]:
        if not self._queue:
            raise RuntimeError("no job is pending")
        key, job = self._queue[0]
        while True:
            try:
                result = self._fn(job)
            except Exception:
                self._retries.failed(key, traceback.format_exc())
                continue
            self._queue.popleft()
            return key, result

    def retire_idle(self) -> int:
        return 0  # the only worker is this process

    def close(self) -> None:
        self._queue.clear()


def _worker_main(
    conn: Connection, function: str, env: Mapping[str, str], log_level: int = logging.WARNING
) -> None:
    """A local worker: set the environment and the log format, import the job function, run
    jobs until None."""
    for name, value in env.items():
        os.environ.setdefault(name, value)
    configure_worker_logging(log_level)
    fn = resolve(function)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        key, job = message
        try:
            reply = (key, True, fn(job))
        except BaseException:
            reply = (key, False, traceback.format_exc())
        conn.send(reply)


@dataclass
class _Slot:
    process: Any
    conn: Connection
    key: Hashable | None = None
    job: Any = None


@dataclass
class PoolStats:
    started: int = 0
    died: int = 0
    deaths: list[str] = field(default_factory=list)


class LocalPool:
    """``workers`` spawned processes, one job each at a time; a dead one is replaced and its
    job alone runs again."""

    backend = "local"

    def __init__(
        self,
        function: str,
        workers: int,
        max_attempts: int = 3,
        env: Mapping[str, str] | None = None,
    ):
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        self.function = function
        self.capacity = int(workers)
        self.env = {**WORKER_ENV, **(env or {})}
        self._ctx = mp.get_context("spawn")
        self._slots: list[_Slot | None] = [None] * self.capacity
        self._retiring: list[_Slot] = []  # told to exit (retire_idle), joined at close
        self._queue: deque[tuple[Hashable, Any]] = deque()
        self._retries = _Retries(max_attempts)
        self.stats = PoolStats()
        self.log_level = logging.getLogger().getEffectiveLevel()

    @property
    def pending(self) -> int:
        return len(self._queue) + sum(s is not None and s.key is not None for s in self._slots)

    @property
    def retried(self) -> int:
        return self._retries.retried

    def submit(self, key: Hashable, job: Any) -> None:
        self._queue.append((key, job))
        self._dispatch()

    def _start(self) -> _Slot:
        parent, child = self._ctx.Pipe(duplex=True)
        process = self._ctx.Process(
            target=_worker_main,
            args=(child, self.function, self.env, self.log_level),
            name="beavr-worker",
            # Not daemonic: a job may start processes of its own (LeRobot encodes the videos
            # of several cameras in a process pool). A worker still ends with this process:
            # its pipe closes, and close() stops it.
            daemon=False,
        )
        process.start()
        child.close()
        self.stats.started += 1
        return _Slot(process, parent)

    def _dispatch(self) -> None:
        for i, slot in enumerate(self._slots):
            if not self._queue:
                return
            if slot is not None and slot.key is not None:
                continue
            if slot is None:
                slot = self._slots[i] = self._start()
            key, job = self._queue.popleft()
            slot.key, slot.job = key, job
            try:
                slot.conn.send((key, job))
            except (BrokenPipeError, OSError):
                self._died(i, slot)

    def _died(self, i: int, slot: _Slot) -> None:
        """Worker ``i`` is gone: its job (if any) goes back to the front of the queue."""
        slot.process.join(timeout=5.0)
        code = slot.process.exitcode
        slot.conn.close()
        self._slots[i] = None
        self.stats.died += 1
        self.stats.deaths.append(f"pid {slot.process.pid} exit code {code} on job {slot.key!r}")
        if slot.key is not None:
            key, job = slot.key, slot.job
            self._retries.failed(key, f"worker process {slot.process.pid} died (exit code {code})")
            self._queue.appendleft((key, job))

    def next_result(self) -> tuple[Hashable, Any]:
        while True:
            self._dispatch()
            busy = [
                (i, s) for i, s in enumerate(self._slots) if s is not None and s.key is not None
            ]
            if not busy:
                raise RuntimeError("no job is pending")
            ready = set(wait([s.conn for _, s in busy] + [s.process.sentinel for _, s in busy]))
            for i, slot in busy:
                if slot.conn in ready:
                    try:
                        key, ok, value = slot.conn.recv()
                    except (EOFError, OSError):
                        self._died(i, slot)
                        break
                    job = slot.job
                    slot.key = slot.job = None
                    if ok:
                        return key, value
                    self._retries.failed(key, value)
                    self._queue.appendleft((key, job))
                    break
                if slot.process.sentinel in ready:
                    self._died(i, slot)
                    break

    def retire_idle(self) -> int:
        """Let every worker without a job exit now, without waiting for it (no more work
        is coming for it: a job submitted later starts a fresh worker). It frees its core
        and memory for the others while they finish; returns how many were retired."""
        retired = 0
        for i, slot in enumerate(self._slots):
            if slot is not None and slot.key is None:
                self._signal_exit(slot)
                self._retiring.append(slot)
                self._slots[i] = None
                retired += 1
        return retired

    @staticmethod
    def _signal_exit(slot: _Slot) -> None:
        if slot.key is None:
            try:
                slot.conn.send(None)
            except (BrokenPipeError, OSError):
                pass
        else:
            slot.process.terminate()

    def close(self) -> None:
        """Stop the workers (a job still running is abandoned). All are told first and then
        waited for, so they exit side by side (a worker's exit, tearing down torch and its
        renderer, takes a second or two here)."""
        self._queue.clear()
        live = [s for s in self._slots if s is not None]
        for slot in live:  # (the retired ones were told already)
            self._signal_exit(slot)
        for slot in live + self._retiring:
            slot.process.join(timeout=10.0)
            if slot.process.is_alive():
                slot.process.kill()
                slot.process.join(timeout=5.0)
            slot.conn.close()
        self._slots = [None] * self.capacity
        self._retiring = []


def require_ray():
    try:
        import ray
    except ImportError as exc:
        raise ImportError(RAY_MISSING) from exc
    return ray


def _forwarded_env(env: Mapping[str, str] | None) -> dict[str, str]:
    forwarded = {k: os.environ[k] for k in FORWARDED_ENV if k in os.environ}
    return {**WORKER_ENV, **forwarded, **(env or {})}


def connect_ray(
    address: str | None = None, in_flight: int | None = None, env: Mapping[str, str] | None = None
) -> None:
    """``ray.init`` as :class:`RayExecutor` does it: the cluster at ``address`` (None:
    ``RAY_ADDRESS`` if set, else a private local instance of ``in_flight`` CPUs, even if
    `ray start` left one running), the workers' environment forwarded. An executor made
    while Ray is initialised uses that connection and leaves it open."""
    ray = require_ray()
    kwargs: dict[str, Any] = {
        "runtime_env": {"env_vars": _forwarded_env(env)},
        "include_dashboard": False,
        "log_to_driver": False,
    }
    address = address or os.environ.get("RAY_ADDRESS")
    if address is None:
        kwargs["address"] = "local"
        kwargs["num_cpus"] = in_flight or os.cpu_count() or 1
    else:
        kwargs["address"] = address
    ray.init(**kwargs)


class RayExecutor:
    """One Ray task per job; Ray retries a task whose worker died or that raised."""

    backend = "ray"

    def __init__(
        self,
        function: str,
        address: str | None = None,
        in_flight: int | None = None,
        max_attempts: int = 3,
        env: Mapping[str, str] | None = None,
    ):
        ray = require_ray()
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            connect_ray(address, in_flight, env)
            self._started = True
        fn = resolve(function)
        self._task = ray.remote(fn).options(
            num_cpus=1, max_retries=max_attempts - 1, retry_exceptions=True
        )
        self.max_attempts = max_attempts
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.capacity = int(in_flight) if in_flight else max(1, cpus)
        self._refs: dict[Any, Hashable] = {}
        #: Ray retries on its own and does not say how often: not counted here.
        self.retried = 0

    @property
    def pending(self) -> int:
        return len(self._refs)

    def submit(self, key: Hashable, job: Any) -> None:
        self._refs[self._task.remote(job)] = key

    def next_result(self) -> tuple[Hashable, Any]:
        if not self._refs:
            raise RuntimeError("no job is pending")
        ray = self._ray
        (ref,), _ = ray.wait(list(self._refs), num_returns=1)
        key = self._refs.pop(ref)
        try:
            return key, ray.get(ref)
        except ray.exceptions.RayError as exc:
            raise JobFailed(key, self.max_attempts, str(exc)) from exc

    def retire_idle(self) -> int:
        return 0  # Ray schedules each task on a worker of its own choosing

    def close(self) -> None:
        for ref in self._refs:
            try:
                self._ray.cancel(ref, force=True)
            except Exception:  # already finished or gone
                pass
        self._refs.clear()
        if self._started:
            self._ray.shutdown()


def make_executor(
    function: str, config: ScaleConfig, env: Mapping[str, str] | None = None
) -> InlineExecutor | LocalPool | RayExecutor:
    """The executor ``config`` asks for, running ``function`` ("module:function")."""
    if config.ray:
        return RayExecutor(
            function, config.ray_address, config.workers, config.max_attempts, env=env
        )
    if config.in_process:
        return InlineExecutor(function, config.max_attempts)
    return LocalPool(function, config.local_workers, config.max_attempts, env=env)
