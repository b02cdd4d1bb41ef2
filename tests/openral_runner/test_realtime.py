"""Real-time knobs: applied best effort, reported, and restored exactly."""

from __future__ import annotations

import os
import sys
import threading

from openral_core import RealtimeConfig
from openral_runner.realtime import apply_realtime, leave_realtime_scheduling


def test_knobs_are_reported_and_restored() -> None:
    before_interval = sys.getswitchinterval()
    before_policy = os.sched_getscheduler(0)
    before_cpus = os.sched_getaffinity(0)
    config = RealtimeConfig(switch_interval_s=0.0007, sched_fifo_priority=10, cpu_affinity=sorted(before_cpus)[:1])
    settings = apply_realtime(config)
    try:
        assert sys.getswitchinterval() == 0.0007
        assert set(settings.report) == {"switch_interval_s", "sched_fifo_priority", "cpu_affinity"}
        if settings.report["sched_fifo_priority"] == "applied":
            assert os.sched_getscheduler(0) == os.SCHED_FIFO
        else:  # no permission: a warning and a report, never an exception
            assert settings.report["sched_fifo_priority"].startswith("failed")
            assert os.sched_getscheduler(0) == before_policy
        assert os.sched_getaffinity(0) == set(config.cpu_affinity or ())
    finally:
        settings.restore()
    assert sys.getswitchinterval() == before_interval
    assert os.sched_getscheduler(0) == before_policy
    assert os.sched_getaffinity(0) == before_cpus
    settings.restore()  # idempotent


def test_threads_leave_an_inherited_realtime_policy() -> None:
    settings = apply_realtime(RealtimeConfig(sched_fifo_priority=5))
    try:
        policies: list[int] = []

        def worker() -> None:
            leave_realtime_scheduling()
            policies.append(os.sched_getscheduler(0))

        thread = threading.Thread(target=worker)
        thread.start()
        thread.join()
        assert policies == [os.SCHED_OTHER]
    finally:
        settings.restore()
