"""Frames completed in this process or in spawned worker processes, handed back in input order."""
from __future__ import annotations

import multiprocessing
import signal
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Generic, TypeVar

import numpy as np

from gd_completion.geometry import Box3D
from gd_completion.settings import CompletionSettings

T = TypeVar("T")

_worker_completer: Any = None
_worker_error: BaseException | None = None


def _init_worker(settings: CompletionSettings) -> None:
    """Process pool initializer: one completer per worker process; a failure is kept and raised by each task."""
    global _worker_completer, _worker_error
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle (it shuts the pool down)
    try:
        from gd_completion.pipeline import VehicleCompleter

        _worker_completer = VehicleCompleter.from_settings(settings)
    except Exception as error:  # noqa: BLE001 - raised in the main process by every task
        _worker_error = error


def _in_worker(task: Callable[..., Any], *args: Any) -> Any:
    """Run `task(completer, *args)` with this worker's completer."""
    if _worker_error is not None:
        raise _worker_error
    return task(_worker_completer, *args)


def _complete(completer: Any, points: np.ndarray, boxes: list[Box3D], stamp_ns: int | None) -> Any:
    if stamp_ns is None:    # any object with complete_frame(points, boxes) serves (the stamp is for track fusion)
        return completer.complete_frame(points, boxes)
    return completer.complete_frame(points, boxes, stamp_ns=stamp_ns)


class FramePool:
    """`submit(points, boxes)` completes one frame: with workers=1 at once, in this process, with `completer`
    (default: made from `settings`, vehicles on its threads); else in `workers` spawned processes (not forked:
    torch and its threads), each with its own completer from `settings` (1 vehicle thread by default).
    """

    def __init__(self, workers: int, settings: CompletionSettings, completer: Any = None) -> None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if completer is not None and workers > 1:
            raise ValueError("an injected completer runs in this process: use workers=1 with completer=")
        self.workers = workers
        self._pool: ProcessPoolExecutor | None = None
        if workers > 1:
            settings = replace(settings, num_threads=settings.num_threads or 1)
            self._pool = ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_init_worker, initargs=(settings,))
        elif completer is None:
            from gd_completion.pipeline import VehicleCompleter

            completer = VehicleCompleter.from_settings(settings)
        self.completer = completer

    def run(self, task: Callable[..., T], *args: Any) -> Future[T]:
        """`task(completer, *args)` (a module-level function when workers > 1); errors with workers=1 raise here."""
        if self._pool is not None:
            return self._pool.submit(_in_worker, task, *args)
        future: Future[T] = Future()
        future.set_result(task(self.completer, *args))
        return future

    def submit(self, points: np.ndarray, boxes: list[Box3D], stamp_ns: int | None = None) -> Future:
        """Complete one frame (stamped: the completer's track fusion, if any, uses it) -> Future of its
        FrameCompletion."""
        return self.run(_complete, points, boxes, stamp_ns)

    def close(self) -> None:
        """Stop the worker processes (pending frames are cancelled)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> FramePool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class Slot(Generic[T]):
    """A queued item; one that `awaits` leaves only with the result of its future, once it has one."""

    item: T
    awaits: bool = False
    future: Future | None = None


class InOrder(Generic[T]):
    """Items leave in the order they were put; an item awaiting a result holds back the ones behind it.

    At most `max_in_flight` started items are pending: `ready()` waits for the oldest beyond that, so memory
    stays flat however long the input is.
    """

    def __init__(self, max_in_flight: int) -> None:
        self.max_in_flight = max_in_flight
        self.in_flight = 0
        self._queue: deque[Slot[T]] = deque()

    def put(self, item: T) -> None:
        """Queue an item that is ready as it is."""
        self._queue.append(Slot(item))

    def hold(self, item: T) -> Slot[T]:
        """Queue an item that waits for `start(slot, future)` and then for the future's result."""
        slot = Slot(item, awaits=True)
        self._queue.append(slot)
        return slot

    def start(self, slot: Slot[T], future: Future) -> None:
        """The held `slot` now waits for `future`."""
        slot.future = future
        self.in_flight += 1

    def ready(self) -> Iterator[tuple[T, Any]]:
        """(item, result or None) from the head of the queue while they are ready."""
        return self._drain(self.max_in_flight - 1)

    def rest(self) -> Iterator[tuple[T, Any]]:
        """Everything left, waiting for each result (every held item must have been started)."""
        return self._drain(-1)

    def _drain(self, limit: int) -> Iterator[tuple[T, Any]]:
        while self._queue:
            head = self._queue[0]
            result = None
            if head.awaits:
                if head.future is None:
                    if limit < 0:
                        raise RuntimeError("InOrder.rest(): an item was held and never started")
                    return
                if self.in_flight <= limit and not head.future.done():
                    return
                result = head.future.result()
                self.in_flight -= 1
            self._queue.popleft()
            yield head.item, result
