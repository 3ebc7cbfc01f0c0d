"""Where scenes are built: in this process, in a local process pool, or as Ray tasks.

Every executor runs the same function on the same units and hands results back in submission
order, so the shard writer sees the same stream of scenes, and writes the same bytes, whichever
runs them. Submission is lazy and bounded (``window`` scenes in flight): the driver claims a
shard only when there is room to start its scenes, which leaves the others to other processes.
"""

from __future__ import annotations

import multiprocessing as mp
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

from usl.errors import UslError

Tag = TypeVar("Tag")
EXECUTORS = ("local", "ray")


class LocalExecutor:
    """``workers == 1``: inline, one scene at a time; else a spawn pool (no forked GL contexts,
    torch thread pools or open file handles in the workers)."""

    def __init__(self, workers: int, initializer: Callable[[], None]):
        self.workers, self.initializer = workers, initializer
        self.pool = None

    def __enter__(self) -> LocalExecutor:
        if self.workers > 1:
            self.pool = mp.get_context("spawn").Pool(self.workers, initializer=self.initializer)
        else:
            self.initializer()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.pool is not None:
            self.pool.terminate()  # stops the workers first: nothing writes spills any more
            self.pool.join()

    @property
    def window(self) -> int:
        return 1 if self.pool is None else 2 * self.workers

    def submit(self, fn: Callable[[Any], Any], unit: Any) -> Callable[[], Any]:
        if self.pool is None:
            return lambda: fn(unit)  # runs when its result is wanted: one scene in flight
        return self.pool.apply_async(fn, (unit,)).get


_worker_ready = False


def _ray_task(fn: Callable[[Any], Any], initializer: Callable[[], None], unit: Any) -> Any:
    """One scene in a Ray worker process; the pipeline's initializer runs once per process."""
    global _worker_ready
    if not _worker_ready:
        initializer()
        _worker_ready = True
    return fn(unit)


class RayExecutor:
    """Scenes as Ray tasks (one CPU each) on the cluster at ``address`` (None: a local instance).

    Results travel through Ray's object store, so workers need not see this machine's disk; the
    shards are written here, by the driver, exactly as with ``--executor local``.
    """

    def __init__(self, address: str | None, initializer: Callable[[], None]):
        try:
            import ray
        except ImportError:
            raise UslError("--executor ray needs the ray package: pip install 'usl[ray]'") from None
        self.ray, self.address, self.initializer = ray, address, initializer
        self.started = False

    def __enter__(self) -> RayExecutor:
        if not self.ray.is_initialized():
            try:
                self.ray.init(address=self.address, include_dashboard=False, log_to_driver=False)
            except ConnectionError as exc:
                raise UslError(f"--ray-address {self.address}: cannot connect to a Ray cluster ({exc})") from None
            self.started = True
        self.task = self.ray.remote(num_cpus=1, max_retries=0)(_ray_task)
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.started:
            self.ray.shutdown()

    @property
    def window(self) -> int:
        return 2 * max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    def submit(self, fn: Callable[[Any], Any], unit: Any) -> Callable[[], Any]:
        ref = self.task.remote(fn, self.initializer, unit)
        return lambda: self.ray.get(ref)


def make_executor(
    name: str, workers: int, ray_address: str | None, initializer: Callable[[], None]
) -> LocalExecutor | RayExecutor:
    return RayExecutor(ray_address, initializer) if name == "ray" else LocalExecutor(workers, initializer)


def ordered_results(
    executor: LocalExecutor | RayExecutor, fn: Callable[[Any], Any], items: Iterable[tuple[Tag, Any]]
) -> Iterator[tuple[Tag, Any]]:
    """``(tag, fn(unit))`` for each ``(tag, unit)`` of ``items``, in order, at most ``window`` in flight.

    ``items`` is drawn only when a slot is free, so its side effects (claiming a shard) happen
    just in time.
    """
    pending: deque[tuple[Tag, Callable[[], Any]]] = deque()
    window = executor.window
    for tag, unit in items:
        pending.append((tag, executor.submit(fn, unit)))
        if len(pending) >= window:
            tag, result = pending.popleft()
            yield tag, result()
    while pending:
        tag, result = pending.popleft()
        yield tag, result()
