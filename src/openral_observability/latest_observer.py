"""``LatestPerKeyObserver``: the newest item per key wins; a worker thread handles it.

The second queue discipline beside :class:`~openral_observability.queued_observer.QueuedObserver`
(every tick, in order). Thumbnails, detectors and live image views want the freshest frame of each
camera, not a backlog: an item offered while an older one of the same key still waits replaces it
(counted in :attr:`replaced`), so the work can never fall behind by more than one item per key.
The offering thread pays one dictionary store per offer and a wake-up only when a key had nothing
pending. :meth:`close` hands what is pending to the worker and stops it; :meth:`start` restarts it,
so a runner can be activated again.

:class:`LatestPerKeyWorker` is the discipline alone, for a part fed from elsewhere than the ticks
(a GStreamer leg, another observer); :class:`LatestPerKeyObserver` is that worker fed by the ticks.
"""

from __future__ import annotations

import threading
from collections.abc import Hashable
from typing import Any, Generic, TypeVar

import structlog

from openral_core import TickResult, WorldState
from openral_observability.observer import TickObserver

_log = structlog.get_logger(__name__)

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class LatestPerKeyWorker(Generic[K, V]):
    """A worker thread that handles the newest item of each key (a camera, a detector kind).

    Callers :meth:`offer` items from any thread; :meth:`handle_item` does the work on the worker
    thread, one key's newest item at a time. A handler that raises is logged and counted in
    :attr:`errors`; the worker goes on.

    Args:
        name: Worker thread name, for logs and debuggers.
        close_timeout_s: How long :meth:`close` waits for the worker to finish what is pending.
    """

    def __init__(self, *, name: str, close_timeout_s: float = 5.0) -> None:
        self._name = name
        self._close_timeout_s = close_timeout_s
        self._pending: dict[K, V] = {}
        self._cond = threading.Condition()
        self._stopping = False
        self._closed = False
        self._thread: threading.Thread | None = None
        self.replaced = 0
        """Items overwritten by a newer one of the same key before the worker reached them."""
        self.handled = 0
        """Items the worker handled."""
        self.errors = 0
        """Items whose handler raised."""

    # -- any thread ------------------------------------------------------------------------

    def offer(self, key: K, item: V) -> None:
        """Make ``item`` the newest of ``key``; O(1), never blocks on the worker's work."""
        with self._cond:
            if key in self._pending:
                self.replaced += 1
                self._pending[key] = item
                return  # the worker was already woken for this key
            self._pending[key] = item
            self._cond.notify()

    def start(self) -> None:
        """Start (or restart) the worker. Idempotent."""
        with self._cond:
            if self._thread is not None and self._thread.is_alive():
                return  # running, or still finishing a close that timed out: never a second worker
            self._stopping = False
            self._closed = False
            self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Let the worker handle what is pending, then stop it and run :meth:`handle_close`. Idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            thread = self._thread
            self._stopping = True
            self._cond.notify()
        if thread is not None:
            thread.join(self._close_timeout_s)
            if thread.is_alive():
                _log.error("observer did not finish in time", observer=self._name, timeout_s=self._close_timeout_s)
            else:
                self._thread = None
        else:
            self._drain()  # never started: what was offered is still handled, on the caller's thread
            self._guarded(self.handle_close)

    @property
    def pending(self) -> int:
        """Keys with an item waiting for the worker."""
        return len(self._pending)

    # -- subclass hooks (worker thread) ----------------------------------------------------

    def handle_item(self, key: K, item: V) -> None:
        """Do the work for the newest item of one key."""
        raise NotImplementedError

    def handle_close(self) -> None:
        """Everything pending was handled; release resources."""

    # -- internals ---------------------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._stopping:
                    self._cond.wait()
                stopping = self._stopping
            self._drain()
            if stopping:
                self._guarded(self.handle_close)
                return

    def _drain(self) -> None:
        with self._cond:
            pending, self._pending = self._pending, {}
        for key, item in pending.items():
            self._guarded(self.handle_item, key, item)
            self.handled += 1

    def _guarded(self, handler: Any, *args: Any) -> None:
        try:
            handler(*args)
        except Exception as exc:  # one bad item must not stop the observer
            self.errors += 1
            _log.error("observer failed on an item", observer=self._name, error=str(exc))
            _log.debug("observer failure", observer=self._name, exc_info=exc)  # the traceback: --debug only


class LatestPerKeyObserver(LatestPerKeyWorker[K, V], TickObserver):
    """A :class:`LatestPerKeyWorker` fed by the ticks: subclasses pick items in :meth:`on_tick` and offer them.

    :meth:`on_tick` runs on the tick thread: take references, touch no pixels.
    """

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Pick and :meth:`offer` items from one tick (tick thread); the default takes nothing."""
