"""Stop signals: any number of SIGINT/SIGTERM lead to one orderly stop, with a bounded escape.

A service manager or a terminal signals the whole process group, and ``uv run`` forwards a second
copy to its child, so a runner must expect the same signal twice within milliseconds, and more
while it is already stopping. :class:`StopSignals` keeps one handler installed for the whole
command, from before the robot connects until telemetry is flushed:

* the first signal asks for an orderly stop (the current tick finishes, the robot holds, every
  component closes, telemetry is flushed, the ``RunResult`` is printed), whatever phase the
  command is in; start-up checks it between steps and rolls back what it opened;
* copies arriving within :data:`DUPLICATE_WINDOW_S` of the last counted signal are the same request;
* later signals only remind the user that the stop is under way, except that two of them within
  :data:`FORCE_WINDOW_S` force the escape: the registered emergency actions (the robot's torque
  off) run with a deadline and the process exits at once.

Signals are read on a watcher thread through :func:`signal.set_wakeup_fd`, so they are seen even
while the main thread is stuck in a C call or a bus transaction: the escape works when nothing
else does.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable
from types import FrameType, TracebackType
from typing import Final, Self

from openral_core import ROSStopRequested

DUPLICATE_WINDOW_S: Final = 0.3
"""Signals this soon after the last counted one are the same request: a group-wide delivery plus the
copy ``uv run`` forwards (SIGTERM at once, SIGINT about 0.2 s later, measured with uv 0.13)."""

FORCE_WINDOW_S: Final = 1.0
"""Two further signals this close together, after the first, force the escape."""

FORCE_DEADLINE_S: Final = 1.0
"""How long the emergency actions may take before the process exits anyway."""

STOP_SIGNALS: Final = (signal.SIGINT, signal.SIGTERM)

_EXIT_CODES: Final = {signal.SIGINT: 130, signal.SIGTERM: 143}


class StopSignals:
    """Install the stop-signal handling for the duration of a ``with`` block (main thread only).

    Args:
        say: Where messages to the user go (a line each); stderr by default.
        exit_process: Called with the exit code after a forced escape; ``os._exit`` by default.
    """

    def __init__(
        self,
        *,
        say: Callable[[str], None] | None = None,
        exit_process: Callable[[int], None] = os._exit,
    ) -> None:
        self._say = say or _write_stderr
        self._exit_process = exit_process
        self._lock = threading.Lock()
        self._first: signal.Signals | None = None
        self._press_at = float("-inf")
        self._extra_at = float("-inf")
        self._stop_callbacks: list[Callable[[str], None]] = []
        self._force_callbacks: list[Callable[[], None]] = []
        self._previous: dict[signal.Signals, object] = {}
        self._previous_wakeup = -1
        self._pipe: tuple[int, int] | None = None
        self._watcher: threading.Thread | None = None
        self.forced = False

    # -- state ----------------------------------------------------------------------------------

    @property
    def received(self) -> signal.Signals | None:
        """The first stop signal, or ``None``."""
        return self._first

    @property
    def reason(self) -> str | None:
        """``signal:SIGINT`` / ``signal:SIGTERM`` once a stop signal arrived (a runner's stop reason)."""
        return None if self._first is None else f"signal:{self._first.name}"

    @property
    def exit_code(self) -> int | None:
        """130 for SIGINT, 143 for SIGTERM, once one arrived."""
        return None if self._first is None else _EXIT_CODES[self._first]

    def check(self) -> None:
        """Raise if a stop signal arrived: called between start-up steps.

        Raises:
            ROSStopRequested: Carrying the stop reason.
        """
        reason = self.reason
        if reason is not None:
            raise ROSStopRequested(f"stopped by {reason.removeprefix('signal:')} during start-up", reason=reason)

    def on_stop(self, callback: Callable[[str], None]) -> None:
        """Call ``callback(reason)`` on the first stop signal (at once if it already arrived)."""
        with self._lock:
            self._stop_callbacks.append(callback)
            reason = self.reason
        if reason is not None:
            callback(reason)

    def on_force(self, callback: Callable[[], None]) -> None:
        """Run ``callback`` (e.g. the robot's torque off) before a forced exit."""
        with self._lock:
            self._force_callbacks.append(callback)

    # -- installation ---------------------------------------------------------------------------

    def __enter__(self) -> Self:
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        self._pipe = (read_fd, write_fd)
        self._previous = {sig: signal.signal(sig, _ignore) for sig in STOP_SIGNALS}
        self._previous_wakeup = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        self._watcher = threading.Thread(target=self._watch, args=(read_fd,), name="openral-signals", daemon=True)
        self._watcher.start()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        signal.set_wakeup_fd(self._previous_wakeup)
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)  # type: ignore[arg-type]
        if self._pipe is not None:
            read_fd, write_fd = self._pipe
            os.close(write_fd)  # the watcher sees end of input and returns
            if self._watcher is not None:
                self._watcher.join(timeout=1.0)
            os.close(read_fd)
            self._pipe = None

    # -- the watcher ------------------------------------------------------------------------------

    def _watch(self, read_fd: int) -> None:
        while True:
            try:
                data = os.read(read_fd, 64)
            except OSError:
                return
            if not data:
                return
            for number in data:
                if number in (signal.SIGINT, signal.SIGTERM):
                    self.deliver(signal.Signals(number), time.monotonic())

    def deliver(self, sig: signal.Signals, now: float) -> None:
        """Account for one stop signal received at ``now`` (monotonic seconds)."""
        with self._lock:
            if now - self._press_at < DUPLICATE_WINDOW_S:
                return
            self._press_at = now
            first = self._first is None
            if first:
                self._first = sig
                callbacks = list(self._stop_callbacks)
            else:
                force = now - self._extra_at <= FORCE_WINDOW_S
                self._extra_at = now
        if first:
            self._say(
                f"{sig.name}: stopping after this tick; the robot holds, then everything closes "
                f"(signal twice more within {FORCE_WINDOW_S:g} s to force torque off and exit now)"
            )
            for callback in callbacks:
                callback(f"signal:{sig.name}")
        elif force:
            self._force()
        else:
            self._say(
                f"{sig.name}: already stopping (once more within {FORCE_WINDOW_S:g} s forces torque off and exit)"
            )

    def _force(self) -> None:
        """Run the emergency actions with a deadline, then exit the process (once)."""
        if self.forced:
            return
        self.forced = True
        self._say(f"forced stop: turning torque off and exiting within {FORCE_DEADLINE_S:g} s")
        with self._lock:
            callbacks = list(self._force_callbacks)
        worker = threading.Thread(target=_run_all, args=(callbacks, self._say), name="openral-force-stop", daemon=True)
        worker.start()
        worker.join(FORCE_DEADLINE_S)
        code = self.exit_code or 1
        self._exit_process(code)


def _run_all(callbacks: list[Callable[[], None]], say: Callable[[str], None]) -> None:
    for callback in callbacks:
        try:
            callback()
        except Exception as exc:  # every emergency action gets its chance
            say(f"emergency action failed: {exc}")


def _ignore(_signum: int, _frame: FrameType | None) -> None:
    """Python-level handler: the watcher thread does the work (see :func:`signal.set_wakeup_fd`)."""


def _write_stderr(text: str) -> None:
    with contextlib.suppress(OSError):
        os.write(2, (text + "\n").encode())
