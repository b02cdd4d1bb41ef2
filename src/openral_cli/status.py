"""The live status of a running deployment: a ``rich`` panel on a terminal, plain lines otherwise.

Written to stderr (the caller passes the stream), so stdout stays clean for ``--json``.
"""

from __future__ import annotations

import threading
from typing import IO, Protocol

from rich.console import Console, Group
from rich.live import Live
from rich.text import Text


class _Observable(Protocol):
    def live_status(self) -> dict[str, float]: ...


def format_status(status: dict[str, float]) -> str:
    """One plain line: rate, tick percentiles and fault counters."""
    return (
        f"ticks {int(status['ticks'])}  rate {status['recent_rate_hz']:.2f}/{status['target_hz']:g} Hz  "
        f"tick p50 {status['tick_ms_p50']:.2f} ms  p99 {status['tick_ms_p99']:.2f} ms  "
        f"late {int(status['deadline_misses'])}  missed slots {int(status['missed_slots'])}  "
        f"dropped {int(status['dropped_actions'])}  stale sensors {int(status['stale_sensors'])} "
        f"(reads {int(status['stale_reads'])})  safety {int(status['safety_violations'])}"
    )


def render_status(status: dict[str, float], title: str = "openral") -> Group:
    """Three short styled lines for a terminal; fault counters turn yellow (red for safety) once non-zero."""
    target = status["target_hz"]
    rate = status["recent_rate_hz"]
    on_rate = target > 0 and abs(rate - target) <= 0.02 * target
    head = Text.assemble(
        (f"{title} ", "bold"),
        f"ticks {int(status['ticks'])}  rate ",
        (f"{rate:.2f}", "green" if on_rate else "yellow"),
        f"/{target:g} Hz  tick p50 ",
        (f"{status['tick_ms_p50']:.2f}", "cyan"),
        " ms  p99 ",
        (f"{status['tick_ms_p99']:.2f}", "cyan"),
        " ms",
    )
    timing = _counters(
        status,
        (
            ("deadline misses", "deadline_misses", "yellow"),
            ("missed slots", "missed_slots", "yellow"),
            ("dropped", "dropped_actions", "yellow"),
        ),
    )
    faults = _counters(
        status,
        (
            ("stale sensors", "stale_sensors", "yellow"),
            ("stale reads", "stale_reads", "yellow"),
            ("safety violations", "safety_violations", "bold red"),
        ),
    )
    return Group(head, timing, faults)


def _counters(status: dict[str, float], items: tuple[tuple[str, str, str], ...]) -> Text:
    """``label value`` pairs; a value is green at zero and ``alarm``-styled otherwise."""
    text = Text("  ")
    for label, key, alarm in items:
        value = int(status[key])
        text.append(f"{label} ")
        text.append(str(value), style=alarm if value else "green")
        text.append("  ")
    return text


class LiveStatus:
    """Shows a runner's live status on ``stream`` between ``__enter__`` and ``__exit__``.

    On a terminal a ``rich`` live panel is refreshed ``refresh_per_second`` times a second,
    and lines written to ``sys.stderr`` meanwhile (logs) scroll above it. Otherwise a plain
    line is printed every ``plain_interval_s`` seconds, so logs stay readable.

    Args:
        runner: Anything with ``live_status()``.
        stream: Where to draw (the CLI passes ``sys.stderr``).
        title: Shown first on the terminal panel.
        refresh_per_second: Terminal refresh rate.
        plain_interval_s: Period of the plain lines.
        console: A preconfigured console (tests force a terminal this way).
    """

    def __init__(
        self,
        runner: _Observable,
        stream: IO[str],
        *,
        title: str = "openral",
        refresh_per_second: float = 2.0,
        plain_interval_s: float = 5.0,
        console: Console | None = None,
    ) -> None:
        self._runner = runner
        self._stream = stream
        self._title = title
        self._console = console or Console(file=stream)
        self._live: Live | None = None
        if self._console.is_terminal:
            self._live = Live(
                get_renderable=self._render,
                console=self._console,
                refresh_per_second=refresh_per_second,
                redirect_stdout=False,
                redirect_stderr=True,
            )
        self._interval = plain_interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def is_live(self) -> bool:
        """Whether the terminal panel is used (rather than plain lines)."""
        return self._live is not None

    def __enter__(self) -> LiveStatus:
        if self._live is not None:
            self._live.start(refresh=True)
        else:
            self._thread = threading.Thread(target=self._plain_loop, name="openral-status", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        if self._live is not None:
            self._live.stop()
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _render(self) -> Group:
        return render_status(self._runner.live_status(), self._title)

    def _plain_loop(self) -> None:
        while not self._stop.wait(self._interval):
            self._stream.write(format_status(self._runner.live_status()) + "\n")
            self._stream.flush()
