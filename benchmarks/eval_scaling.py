"""Evaluation scaling: the same expert episodes with one worker and with N, through the CLI.

``openral benchmark run`` evaluates a suite twice on this machine: with ``--workers 1``, then with
``--workers N`` and the first run's report as ``--baseline``, so the second report carries the
speed-up and efficiency (speed-up ÷ N) measured against the first. Both runs pass the same
``--threads-per-worker`` (1 by default: one thread per numeric library in every worker, the
one-worker run in a worker process of its own too), so they differ in the workers alone.

Targets (``--target``), state-only:

* ``so101_pick``: one row, ``scenes/sim/so101_pick.yaml`` with ``so101_pick_expert``, as in
  ``benchmarks/suites/so101.yaml`` (``--episodes`` default 192).
* ``libero``: a LIBERO suite, two rows with ``libero_expert``: ``libero_goal_bowl_on_plate``
  (task 8, short episodes) and ``libero_object`` (task 0), ``--episodes`` each (default 10: a few
  minutes on a 2-core machine; LIBERO's own evaluations run 50 per task). The second row builds
  its environment in every worker within its own time (the first row's is built as the workers
  start), so it is the one with the long episodes, over which that build is spread.

Printed for each run and row: the wall time and episodes per second (its episodes alone: the
workers have started and built the first row's scene), the efficiency, the report's
``startup_s``, the whole command's wall time (interpreter and imports too), and the environments
built. Both runs must give identical outcomes (same seeds); the script says so.

Where the efficiency is below 0.9 the loss is split in two. Each episode reports its mean step
time, so the same steps' total with N workers against one worker says how much slower every
process got by sharing the machine (caches, memory bandwidth, clocks, other programs: the
machine's ceiling, which no scheduling recovers); what remains (efficiency × that slowdown) is
the evaluator's own share: workers idle at a row's end (its last episodes run on fewer workers
than N), environments built inside a row's time (every row after the first, in every worker),
and the cost of each unit.

Run:  uv run python benchmarks/eval_scaling.py [--target so101_pick|libero] [--episodes E] [--workers N]
      [--threads-per-worker T]
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

SCENES = Path(__file__).resolve().parents[1] / "scenes" / "sim"
TARGETS: dict[str, tuple[list[tuple[str, str]], int]] = {
    "so101_pick": ([("so101_pick.yaml", "so101_pick_expert")], 192),
    "libero": ([("libero_goal_bowl_on_plate.yaml", "libero_expert"), ("libero_object.yaml", "libero_expert")], 10),
}
"""Each target's rows (scene file, skill) and its default episodes per row."""
GOAL = 0.9
"""The efficiency aimed at: 0.9 × N episodes per second of one worker, with N workers."""


def _run(suite: Path, out: Path, workers: int, threads: int, baseline: Path | None) -> tuple[dict[str, Any], float]:
    """One ``benchmark run``: its report and the command's wall time."""
    command = [sys.executable, "-m", "openral_cli", "benchmark", "run", "--config", str(suite)]
    command += ["--workers", str(workers), "--threads-per-worker", str(threads), "--out", str(out), "--json"]
    if baseline is not None:
        command += ["--baseline", str(baseline)]
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr[-3000:]}")
    return json.loads(out.read_text()), elapsed


def _step_s(rows: list[dict[str, Any]]) -> float:
    """Seconds spent in the rows' step ticks, summed over their episodes."""
    return sum(e["timing"]["step_ms_mean"] * e["steps"] for row in rows for e in row["episodes"]) / 1e3


def _untimed(rows: list[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    return [[{k: v for k, v in e.items() if k != "timing"} for e in row["episodes"]] for row in rows]


def _suite(folder: Path, target: str, episodes: int) -> Path:
    rows, _ = TARGETS[target]
    lines = [f"  - {{scene: {SCENES / scene}, skill: {skill}, n_episodes: {episodes}}}" for scene, skill in rows]
    suite = folder / "suite.yaml"
    suite.write_text(f"name: eval_scaling_{target}\nruns:\n" + "\n".join(lines) + "\n", encoding="utf-8")
    return suite


def _limits(workers: int, efficiency: float, slowdown: float, rows: list[dict[str, Any]]) -> list[str]:
    """What keeps the efficiency below the goal: the machine's share and the evaluator's, the larger named."""
    machine, evaluator = 1 / slowdown, efficiency * slowdown
    lines = [
        f"below {GOAL}: sharing the machine leaves {machine:.2f} (the same steps ran {slowdown:.2f}x as long), "
        f"the evaluator {evaluator:.2f} (idle workers, builds, per-unit cost)"
    ]
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    load = os.getloadavg()[0]
    if machine < evaluator:
        lines.append(
            f"  the machine limits it: {cpus} CPUs for {workers} workers, load {load:.2f} now "
            "(other programs, or memory bandwidth and clocks shared by the workers); run on a quiet machine"
        )
    else:
        shortest = min(row["n_episodes"] for row in rows)
        lines.append(
            f"  the evaluator limits it: a row's last episodes run on fewer than {workers} workers, and every row "
            f"after the first builds its environment in each worker within its time; with {shortest} episodes in "
            "a row those are a large share: more episodes per row, or fewer rows, raise it"
        )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--target", choices=sorted(TARGETS), default="so101_pick")
    parser.add_argument("--episodes", type=int, default=None, help="Episodes per row (default: the target's).")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--threads-per-worker", type=int, default=1, help="Passed to both runs (0: no limit).")
    args = parser.parse_args()
    rows, default_episodes = TARGETS[args.target]
    episodes = args.episodes or default_episodes
    print(machine_line())
    names = ", ".join(f"{scene.removesuffix('.yaml')} / {skill}" for scene, skill in rows)
    print(f"{names}: {episodes} episodes a row (seeds 0–{episodes - 1}), state-only, ", end="")
    print(f"{args.threads_per_worker or 'unlimited'} thread(s) per library in each worker")

    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        suite = _suite(tmp, args.target, episodes)
        one_out, many_out = tmp / "one.json", tmp / "many.json"
        one, one_command_s = _run(suite, one_out, 1, args.threads_per_worker, None)
        many, many_command_s = _run(suite, many_out, args.workers, args.threads_per_worker, one_out)

    for workers, report, command_s in ((1, one, one_command_s), (args.workers, many, many_command_s)):
        print(
            f"{workers:3d} worker(s): start-up {report['startup_s']:5.2f} s, command {command_s:7.2f} s, "
            f"{report['provenance']['threads_per_worker']} thread(s) per library "
            f"(a worker's OMP_NUM_THREADS: {report['provenance']['worker_threads']['variables']['OMP_NUM_THREADS']})"
        )
        for row in report["results"]:
            efficiency = "—" if row["efficiency"] is None else f"{row['efficiency']:.2f}"
            print(
                f"    {row['label']}: {row['wall_s']:7.2f} s = {row['episodes_per_s']:6.2f} episodes/s "
                f"({row['episodes_per_s_per_worker']:.2f} per worker), efficiency {efficiency}, "
                f"{row['env_builds']} env build(s), {row['n_success']}/{row['n_episodes']} succeeded"
            )
    one_rows, many_rows = one["results"], many["results"]
    total = sum(row["n_episodes"] for row in many_rows)
    speedup = (total / sum(r["wall_s"] for r in many_rows)) / (total / sum(r["wall_s"] for r in one_rows))
    efficiency = speedup / args.workers
    print(
        f"speed-up with {args.workers} workers: {speedup:.2f}x, per-worker efficiency {efficiency:.2f} "
        f"(episodes/s of the rows against the measured one-worker run; goal {GOAL})"
    )
    command_speedup = one_command_s / many_command_s
    print(
        f"whole command: {command_speedup:.2f}x, efficiency {command_speedup / args.workers:.2f} "
        "(interpreter, imports, checks and start-up included)"
    )
    slowdown = _step_s(many_rows) / _step_s(one_rows)
    print(
        f"the same steps took {slowdown:.2f}x as long with {args.workers} workers (sharing the machine); "
        f"efficiency x slowdown = {efficiency * slowdown:.2f} (the evaluator's own share: "
        "idle workers, builds, per-unit cost)"
    )
    if efficiency < GOAL:
        for line in _limits(args.workers, efficiency, slowdown, many_rows):
            print(line)
    print(f"outcomes identical: {'yes' if _untimed(one_rows) == _untimed(many_rows) else 'NO'}")


if __name__ == "__main__":
    main()
