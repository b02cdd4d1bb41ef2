"""Printing a ``RunResult`` for people."""

from __future__ import annotations

from openral_core import RunResult
from openral_runner.sensor_lag import lag_line


def format_run_result(result: RunResult) -> str:
    """A compact multi-line summary with every timing and fault figure."""
    lines = [
        f"run '{result.runner_name}' skill={result.skill_id} stopped: {result.stop_reason}",
        f"  ticks            {result.n_ticks} in {result.duration_s:.3f} s",
        f"  rate             {result.effective_rate_hz:.3f} Hz achieved / {result.rate_hz:g} Hz target",
        f"  tick ms          mean {result.tick_ms_mean:.3f}  p50 {result.tick_ms_p50:.3f}  "
        f"p99 {result.tick_ms_p99:.3f}  max {result.tick_ms_max:.3f}",
        f"  inference ms     mean {result.inference_ms_mean:.3f}  p50 {result.inference_ms_p50:.3f}  "
        f"p99 {result.inference_ms_p99:.3f}  max {result.inference_ms_max:.3f}",
        f"  start jitter us  p50 {result.start_jitter_us_p50:.1f}  p99 {result.start_jitter_us_p99:.1f}  "
        f"max {result.start_jitter_us_max:.1f}",
        f"  overhead us      mean {result.overhead_us_mean:.1f} per tick",
        f"  missed slots {result.missed_slots}  deadline misses {result.deadline_misses}  "
        f"budget violations {result.budget_violations}",
        f"  withheld {result.withheld_actions} (dropped late {result.dropped_actions})  "
        f"failed ticks {result.failed_ticks}  stale reads {result.stale_reads}  "
        f"safety violations {result.safety_violations}",
    ]
    if result.trace_id:
        lines.append(f"  trace id         {result.trace_id}")
    for sensor_id, figures in (result.metadata.get("sensors") or {}).items():
        lag = lag_line(sensor_id, figures)
        if lag is not None:
            lines.append(f"  {lag}")
    return "\n".join(lines)
