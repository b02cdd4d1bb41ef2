"""The live status: a rich panel on a terminal, plain lines otherwise, figures from runner.live_status()."""

from __future__ import annotations

import io
import time
from collections.abc import Callable

from rich.console import Console
from rich.text import Text

from openral_cli.status import LiveStatus, format_status

STATUS = {
    "ticks": 1234.0,
    "target_hz": 30.0,
    "rate_hz": 29.9,
    "recent_rate_hz": 29.97,
    "tick_ms_p50": 1.25,
    "tick_ms_p99": 4.5,
    "deadline_misses": 3.0,
    "missed_slots": 2.0,
    "dropped_actions": 1.0,
    "withheld_actions": 4.0,
    "stale_sensors": 1.0,
    "stale_reads": 17.0,
    "safety_violations": 5.0,
}


def wait_until(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
    """Poll ``condition`` until it holds: the status thread's pace depends on the machine's load."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the status never got there"
        time.sleep(0.005)


class FakeRunner:
    def __init__(self) -> None:
        self.calls = 0

    def live_status(self) -> dict[str, float]:
        self.calls += 1
        return dict(STATUS)


def test_plain_line_has_every_figure() -> None:
    line = format_status(STATUS)
    for text in ("ticks 1234", "29.97/30 Hz", "p50 1.25 ms", "p99 4.50 ms", "late 3", "missed slots 2",
                 "dropped 1", "stale sensors 1 (reads 17)", "safety 5"):  # fmt: skip
        assert text in line, text


def test_plain_lines_when_the_stream_is_not_a_terminal() -> None:
    stream = io.StringIO()
    runner = FakeRunner()
    with LiveStatus(runner, stream, plain_interval_s=0.02) as status:
        assert not status.is_live
        wait_until(lambda: stream.getvalue().count("\n") >= 2)
    lines = stream.getvalue().splitlines()
    assert len(lines) >= 2
    assert all(line == format_status(STATUS) for line in lines)
    assert "\x1b" not in stream.getvalue()


def test_live_panel_on_a_terminal() -> None:
    stream = io.StringIO()
    console = Console(file=stream, force_terminal=True, width=200, color_system="standard")
    runner = FakeRunner()
    with LiveStatus(runner, stream, title="so101_twin", console=console, refresh_per_second=20) as status:
        assert status.is_live
        wait_until(lambda: runner.calls >= 3)
    assert runner.calls >= 3  # refreshed repeatedly, not drawn once
    raw = stream.getvalue()
    assert "\x1b[1;31m5" in raw  # safety violations stand out in bold red
    text = Text.from_ansi(raw).plain
    for figure in ("so101_twin", "ticks 1234", "29.97", "/30 Hz", "1.25", "4.50", "deadline misses 3",
                   "stale sensors 1", "safety violations 5"):  # fmt: skip
        assert figure in text, figure
