"""Evaluation scaling: the same SO-101 pick expert episodes with one worker and with N, through the CLI.

``openral benchmark run`` evaluates a one-row suite (``scenes/sim/so101_pick.yaml``, state-only,
``so101_pick_expert``, as in ``benchmarks/suites/so101.yaml``) twice on this machine: with
``--workers 1``, then with ``--workers N`` and the first run's report as ``--baseline``, so the
second report carries the speed-up and efficiency (speed-up ÷ N) measured against the first.
Printed for each run: the row's wall time and episodes per second (its episodes alone: the
workers have started and built the scene), the report's ``startup_s`` (checking the suite while
the workers start, until they are ready), the whole command's wall time (interpreter and imports
too), and the environments built. Both runs must give identical outcomes (same seeds); the script says so.

The loss is then split in two. Each episode reports its mean step time, so the same steps'
total with N workers against one worker says how much slower every process got by sharing the
machine (caches, memory bandwidth, clocks: the machine's ceiling, which no scheduling recovers);
what remains (efficiency × that slowdown) is the evaluator's own share: idle workers, start-up
and the cost of each unit.

Run:  uv run python benchmarks/eval_scaling.py [--episodes 192] [--workers N (default: the CPU count)]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from _common import machine_line

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "sim" / "so101_pick.yaml"
SKILL = "so101_pick_expert"


def _run(suite: Path, out: Path, workers: int, baseline: Path | None) -> tuple[dict[str, Any], float]:
    """One ``benchmark run``: its report and the command's wall time."""
    command = [sys.executable, "-m", "openral_cli", "benchmark", "run", "--config", str(suite)]
    command += ["--workers", str(workers), "--out", str(out), "--json"]
    if baseline is not None:
        command += ["--baseline", str(baseline)]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return json.loads(out.read_text()), elapsed


def _step_s(row: dict[str, Any]) -> float:
    """Seconds spent in the row's step ticks, summed over its episodes."""
    return sum(e["timing"]["step_ms_mean"] * e["steps"] for e in row["episodes"]) / 1e3


def _untimed(row: dict[str, Any]) -> list[dict[str, Any]]:
    return [{k: v for k, v in e.items() if k != "timing"} for e in row["episodes"]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=192)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    args = parser.parse_args()
    print(machine_line())
    print(f"so101_pick / {SKILL}, {args.episodes} episodes (seeds 0–{args.episodes - 1}), state-only")

    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        suite = tmp / "suite.yaml"
        suite.write_text(
            f"name: eval_scaling\nruns:\n  - {{scene: {SCENE}, skill: {SKILL}, n_episodes: {args.episodes}}}\n",
            encoding="utf-8",
        )
        one_out, many_out = tmp / "one.json", tmp / "many.json"
        one, one_command_s = _run(suite, one_out, 1, None)
        many, many_command_s = _run(suite, many_out, args.workers, one_out)

    (one_row,) = one["results"]
    (many_row,) = many["results"]
    runs = ((1, one, one_row, one_command_s), (args.workers, many, many_row, many_command_s))
    for workers, report, row, command_s in runs:
        print(
            f"{workers:3d} worker(s): row {row['wall_s']:7.2f} s = {row['episodes_per_s']:6.2f} episodes/s "
            f"({row['episodes_per_s_per_worker']:.2f} per worker), start-up {report['startup_s']:5.2f} s, "
            f"command {command_s:7.2f} s, {row['env_builds']} env build(s), "
            f"{row['n_success']}/{row['n_episodes']} succeeded"
        )
    print(
        f"speed-up with {args.workers} workers: {many_row['speedup']:.2f}x, "
        f"efficiency {many_row['efficiency']:.2f} (episodes/s of the rows, from the report's --baseline)"
    )
    command_speedup = one_command_s / many_command_s
    print(
        f"whole command: {command_speedup:.2f}x, efficiency {command_speedup / args.workers:.2f} "
        "(interpreter, imports, checks and start-up included)"
    )
    slowdown = _step_s(many_row) / _step_s(one_row)
    print(
        f"the same steps took {slowdown:.2f}x as long with {args.workers} workers (sharing the machine); "
        f"efficiency x slowdown = {many_row['efficiency'] * slowdown:.2f} (the evaluator's own share: "
        "idle workers, start-up, per-unit cost)"
    )
    print(f"outcomes identical: {'yes' if _untimed(one_row) == _untimed(many_row) else 'NO'}")


if __name__ == "__main__":
    main()
