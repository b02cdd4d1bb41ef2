"""``QueuedObserver``: the tick thread hands references over; a worker thread does the work.

An observer built on it costs the tick thread one ``deque.append`` per tick. Its worker wakes every
``flush_interval_s`` (waking a sleeping thread from the tick thread would cost tens of µs), or at
once for episode boundaries and when the queue is half full, and calls the subclass's handlers in
order. The queue is bounded: when it is full the oldest tick is dropped, counted in
:attr:`overflowed` and passed to :meth:`on_overflow`; episode boundaries are never dropped.
:meth:`close` drains everything queued before it returns.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Final

import structlog

from openral_core import ROSConfigError, TickResult, WorldState
from openral_observability.observer import TickObserver

_log = structlog.get_logger(__name__)

_TICK: Final = 0
_START: Final = 1
_END: Final = 2


class QueuedObserver(TickObserver):
    """Base for observers whose work (encoding, writing, publishing) must stay off the tick thread.

    Subclasses implement :meth:`handle_tick` and, as needed, :meth:`handle_episode_start`,
    :meth:`handle_episode_end` and :meth:`handle_close`; all run on the worker thread, in the order
    the runner called the observer. A handler that raises is logged and counted in :attr:`errors`;
    the worker goes on with the next item.

    Args:
        name: Thread name, for logs and debuggers.
        max_queue: Ticks held before the oldest is dropped.
        flush_interval_s: How often the worker wakes to drain the queue.
        close_timeout_s: How long :meth:`close` waits for the worker to drain.

    Raises:
        ROSConfigError: ``max_queue`` below 2 or ``flush_interval_s`` not positive.
    """

    def __init__(
        self, *, name: str, max_queue: int = 1024, flush_interval_s: float = 0.02, close_timeout_s: float = 30.0
    ) -> None:
        if max_queue < 2:
            raise ROSConfigError(f"must be at least 2, got {max_queue}", field="max_queue")
        if not flush_interval_s > 0:
            raise ROSConfigError(f"must be positive, got {flush_interval_s}", field="flush_interval_s")
        self._items: deque[tuple[int, Any, Any]] = deque()
        # Single-writer counters (no lock on the tick path): appended and dropped by the tick
        # thread, taken by the worker.
        self._appended = 0
        self._taken = 0
        self._max_queue = max_queue
        self._wake_at = max_queue // 2
        self._flush_interval_s = flush_interval_s
        self._close_timeout_s = close_timeout_s
        self._cond = threading.Condition()
        self._closing = False
        self._closed = False
        self.overflowed = 0
        """Ticks dropped because the queue was full."""
        self.errors = 0
        """Items whose handler raised."""
        self.handled = 0
        """Ticks handled by the worker."""
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # -- tick thread -----------------------------------------------------------------------

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Queue a reference to the tick and its world state (O(1); never blocks, never copies)."""
        if self._closing:
            return
        if self.queued >= self._max_queue:
            self._drop_oldest_tick()
        self._items.append((_TICK, tick, world))
        self._appended += 1
        if self.queued == self._wake_at:
            with self._cond:
                self._cond.notify()

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        """Queue an episode start and wake the worker."""
        self._put((_START, episode_idx, task))

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        """Queue an episode end and wake the worker."""
        self._put((_END, episode_idx, (success, keep)))

    def close(self) -> None:
        """Drain the queue, run :meth:`handle_close` on the worker and stop it. Idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closing = True
            self._cond.notify()
        self._thread.join(self._close_timeout_s)
        if self._thread.is_alive():
            _log.error("observer did not drain in time", observer=self._thread.name, timeout_s=self._close_timeout_s)
        self._closed = True

    def wait_for_room(self, timeout_s: float = 30.0) -> bool:
        """Block until the worker has caught up to half the queue: for loops with no deadline (a simulation).

        Returns:
            ``False`` if it did not within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        while self.queued > self._wake_at:
            if time.monotonic() >= deadline or not self._thread.is_alive():
                return False
            with self._cond:
                self._cond.notify()
            time.sleep(0.0005)
        return True

    # -- subclass hooks (worker thread) ------------------------------------------------------

    def handle_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Do the work for one tick."""
        raise NotImplementedError

    def handle_episode_start(self, episode_idx: int, task: str) -> None:
        """An episode began; ticks after this belong to it."""

    def handle_episode_end(self, episode_idx: int, *, success: bool, keep: bool) -> None:
        """The episode ended (``keep=False``: throw it away); later ticks belong to no episode until the next start."""

    def handle_close(self) -> None:
        """Everything queued was handled; release resources."""

    def on_overflow(self, tick: TickResult) -> None:
        """Called on the tick thread with a tick that was dropped because the queue was full."""

    # -- internals ---------------------------------------------------------------------------

    @property
    def queued(self) -> int:
        """Ticks waiting for the worker."""
        return self._appended - self.overflowed - self._taken

    def _put(self, item: tuple[int, Any, Any]) -> None:
        with self._cond:
            if self._closing:
                return
            self._items.append(item)
            self._cond.notify()

    def _drop_oldest_tick(self) -> None:
        with self._cond:
            for index, (kind, tick, _world) in enumerate(self._items):
                if kind == _TICK:
                    del self._items[index]
                    self.overflowed += 1
                    self.on_overflow(tick)
                    return

    def _run(self) -> None:
        while True:
            with self._cond:
                if not self._items and not self._closing:
                    self._cond.wait(self._flush_interval_s)
                closing = self._closing
            while True:
                with self._cond:
                    if not self._items:
                        break
                    kind, first, second = self._items.popleft()
                    if kind == _TICK:
                        self._taken += 1
                self._handle(kind, first, second)
            if closing:
                self._guarded(self.handle_close)
                return

    def _handle(self, kind: int, first: Any, second: Any) -> None:
        if kind == _TICK:
            self._guarded(self.handle_tick, first, second)
            self.handled += 1
        elif kind == _START:
            self._guarded(self.handle_episode_start, first, second)
        else:
            success, keep = second
            self._guarded(self.handle_episode_end, first, success=success, keep=keep)

    def _guarded(self, handler: Any, *args: Any, **kwargs: Any) -> None:
        try:
            handler(*args, **kwargs)
        except Exception as exc:  # one bad item must not stop the observer
            self.errors += 1
            _log.error("observer failed on an item", observer=self._thread.name, error=str(exc))
            _log.debug("observer failure", observer=self._thread.name, exc_info=exc)  # the traceback: --debug only
