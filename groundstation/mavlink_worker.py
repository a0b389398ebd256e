"""One worker thread per MAVLink link that runs the command exchanges that wait for acknowledgements.

The flight supervisor calls ``link.land()`` / ``link.takeoff()`` for every drone from one thread; a vehicle that
does not answer must not hold up the others. So those calls only queue a job here and return its
``concurrent.futures.Future``; the worker runs the jobs in order, each awaiting its acks with timeouts. A job
that is already queued or running under the same name is not queued twice (the supervisor repeats land
commands to a silent vehicle every ``land_retry``); the caller gets the future of the one in flight.
``preempt(names)`` cancels queued jobs of those names and tells a running one to stop at its next wait
(``should_stop``), which is how a landing overtakes a takeoff that hangs on a lost ack.
"""
from __future__ import annotations

import concurrent.futures
import logging
import queue
import threading
from typing import Any, Callable

logger = logging.getLogger(__name__)


class CommandWorker:
    def __init__(self, name: str) -> None:
        self._queue: queue.Queue[tuple[str, Callable[[], Any], concurrent.futures.Future] | None] = queue.Queue()
        self._active: dict[str, concurrent.futures.Future] = {}
        self._lock = threading.Lock()
        self._running: str | None = None
        self._stop_running = threading.Event()
        self.errors: list[str] = []
        """One line per job that failed, oldest first (also logged)."""
        self._thread = threading.Thread(target=self._work, name=name, daemon=True)
        self._thread.start()

    def submit(self, name: str, job: Callable[[], Any]) -> concurrent.futures.Future:
        with self._lock:
            fut = self._active.get(name)
            if fut is not None and not fut.done():
                return fut
            fut = concurrent.futures.Future()
            self._active[name] = fut
        self._queue.put((name, job, fut))
        return fut

    def preempt(self, names: tuple[str, ...]) -> None:
        with self._lock:
            for name in names:
                fut = self._active.get(name)
                if fut is not None:
                    fut.cancel()  # only succeeds while queued
            if self._running in names:
                self._stop_running.set()

    def should_stop(self) -> bool:
        """True when the running job was preempted: it should raise at its next wait."""
        return self._stop_running.is_set()

    def busy(self, name: str) -> bool:
        fut = self._active.get(name)
        return fut is not None and not fut.done()

    def close(self) -> None:
        self._queue.put(None)
        self.preempt(tuple(self._active))
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2.0)

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            name, job, fut = item
            if not fut.set_running_or_notify_cancel():
                continue
            with self._lock:
                self._running = name
                self._stop_running.clear()
            try:
                fut.set_result(job())
            except Exception as exc:  # the job's error goes to whoever holds the future, and to the log
                self.errors.append(f"{name}: {exc}")
                logger.warning("%s failed: %s", name, exc)
                fut.set_exception(exc)
            finally:
                with self._lock:
                    self._running = None
