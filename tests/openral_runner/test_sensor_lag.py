"""Per-sensor read accounting and the one line that says a camera did not keep up, with what to change."""

from __future__ import annotations

from openral_runner.sensor_lag import LAG_STALE_SHARE, SensorReads, lag_line


def _figures(reads: int, stale_ages: list[float | None], **report: object) -> dict[str, object]:
    counts = SensorReads()
    counts.reads = reads
    for age in stale_ages:
        counts.stale_read(age, 250.0)
    return {**report, **counts.summary()}


def test_the_summary_counts_stale_reads_and_their_ages_against_the_limit() -> None:
    figures = _figures(10, [300.0, 400.0, None])
    assert figures == {
        "reads": 10,
        "stale_reads": 3,
        "stale_share": 0.3,
        "stale_age_ms_mean": 350.0,  # the read with no frame at all has no age
        "stale_age_ms_max": 400.0,
        "max_age_ms": 250.0,
    }


def test_a_sensor_within_the_allowed_share_of_stale_reads_kept_up() -> None:
    assert lag_line("front", _figures(300, [])) is None
    allowed = int(300 * LAG_STALE_SHARE)
    assert lag_line("front", _figures(300, [260.0] * allowed)) is None
    assert lag_line("front", _figures(300, [260.0] * (allowed + 1))) is not None


def test_the_line_gives_the_measured_ages_the_limit_the_capture_rate_and_the_backends_advice() -> None:
    figures = _figures(
        300, [292.0, 385.0] * 22, requested_fps=30.0, delivered_fps=8.3, render_ms=103.4, advice="render smaller"
    )
    line = lag_line("front", figures)
    assert line == (
        "sensor 'front' did not keep up: 44 of 300 reads were stale (their frames 338 ms old on average, "
        "up to 385 ms, against max_age_ms 250); it delivered 8.3 of 30 fps, 103 ms per render. "
        "To fix: render smaller; or raise max_age_ms above 250 if the skill tolerates older frames"
    )


def test_without_a_capture_report_the_line_still_names_the_limit_and_a_generic_fix() -> None:
    line = lag_line("wrist", _figures(10, [None, None]))
    assert line is not None
    assert line.startswith("sensor 'wrist' did not keep up: 2 of 10 reads were stale. To fix: lower its fps")
    assert "raise max_age_ms above 250" in line
