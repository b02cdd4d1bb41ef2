"""A live one-line status of a running deployment, refreshed from a background thread."""

from __future__ import annotations

import threading
from typing import IO, Protocol


class _Observable(Protocol):
    def live_status(self) -> dict[str, float]: ...


def format_status(status: dict[str, float]) -> str:
    """One human line: rate, tick percentiles and fault counters."""
    return (
        f"ticks {int(status['ticks'])}  rate {status['rate_hz']:.2f} Hz  "
        f"tick p50 {status['tick_ms_p50']:.2f} ms  p99 {status['tick_ms_p99']:.2f} ms  "
        f"late {int(status['deadline_misses'])}  missed slots {int(status['missed_slots'])}  "
        f"dropped {int(status['dropped_actions'])}  stale {int(status['stale_reads'])}  "
        f"safety {int(status['safety_violations'])}"
    )


class StatusLine:
    """Prints the runner's live status to ``stream`` until stopped.

    On a terminal the line is rewritten in place about twice a second; otherwise a plain line
    is printed every ``plain_interval_s`` so logs stay readable.
    """

    def __init__(
        self,
        runner: _Observable,
        stream: IO[str],
        *,
        interval_s: float = 0.5,
        plain_interval_s: float = 5.0,
    ) -> None:
        self._runner = runner
        self._stream = stream
        self._tty = stream.isatty()
        self._interval = interval_s if self._tty else plain_interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="openral-status", daemon=True)

    def __enter__(self) -> StatusLine:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if self._tty:
            self._stream.write("\n")
            self._stream.flush()

    def _loop(self) -> None:
        while not self._stop.wait(self._interval):
            line = format_status(self._runner.live_status())
            self._stream.write(f"\r\x1b[2K{line}" if self._tty else f"{line}\n")
            self._stream.flush()
