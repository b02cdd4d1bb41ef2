"""What the executor's prefix buys: ACT and act-smooth on SO-101 pick at inference delays d = 0, 1, 2, 4.

Three policy/executor rows on the same seeds of ``scenes/sim/so101_pick.yaml`` (state only), each
through ``openral sim run`` with the scene's virtual latency set per column (``--set
virtual_latency.ticks=d``), so every number reproduces on any machine:

* ACT, stale start: each chunk runs from its first row when it arrives (``executor.indexing:
  stale_start``), as naive executors do;
* ACT, tick-indexed: rows indexed by the tick of their observation (openral's executor), the
  rows for ticks that passed while it inferred skipped;
* act-smooth, tick-indexed + prefix: the same executor, the policy also fed the rows already
  committed for those ticks and the last commands sent.

Each cell is the success rate with its Wilson 95 % interval; the smoothness columns are the seam
jump p95 over episodes (``smoothness.seam_jump_max.p95``), the mean jerk RMS of the commands and the
mean jerk RMS of the end effector's measured path (m/s³). Then, for each
delay, the paired comparisons on the same seeds: tick-indexed against stale start, and act-smooth
against tick-indexed ACT (Newcombe's interval, exact McNemar). ``--real-time`` adds a column in
real-time mode (``--real-time``: wall-clock paced, machine-dependent).

Run (Python 3.12 with the ``lerobot`` extra and ``lerobot-policy-act-smooth`` importable, e.g. the
venv of ``scripts/lerobot_so101/act_smooth.md``):

    python benchmarks/prefix_table.py --act models/so101_pick_act \\
        --act-smooth models/so101_pick_act_smooth [--episodes 50] [--delays 0 1 2 4] [--real-time]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from _common import machine_line
from openral_sim.benchmark.compare import compare_rows

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
REAL_TIME = "real time"


def _sim_run(params: dict[str, Any], episodes: int, settings: list[str], real_time: bool) -> dict[str, Any]:
    """One ``openral sim run --json`` of ``lerobot_policy`` on the scene: its report."""
    command = [
        sys.executable, "-m", "openral_cli", "sim", "run", "--config", str(SCENE), "--skill", "lerobot_policy",
        "--skill-params", json.dumps(params), "--n-episodes", str(episodes), "--no-cameras", "--json",
    ]  # fmt: skip
    for setting in settings:
        command += ["--set", setting]
    if real_time:
        command.append("--real-time")
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}
    done = subprocess.run(command, capture_output=True, text=True, check=False, env=env, cwd=ROOT)
    if done.returncode != 0:
        raise SystemExit(f"sim run failed ({' '.join(settings)}):\n{done.stderr[-2000:]}")
    report: dict[str, Any] = json.loads(done.stdout)
    return report


def _as_row(report: dict[str, Any]) -> dict[str, Any]:
    """A ``sim run`` report in the shape of a benchmark row, for :func:`compare_rows`."""
    seeds = [e["seed"] for e in report["episodes"]]
    return {
        "scene": report["scene"],
        "env": "so101",
        "env_id": "SO101PickCube-v0",
        "seeds": [min(seeds), max(seeds)],
        "timing": report.get("timing"),
        "episodes": report["episodes"],
    }


def _cell(report: dict[str, Any]) -> str:
    low, high = report["pc_success_ci95"]
    return f"{report['pc_success']:.0f} % ({low:.0f}–{high:.0f})"


def _smooth(report: dict[str, Any]) -> str:
    smoothness = report.get("smoothness") or {}
    seam = (smoothness.get("seam_jump_max") or {}).get("p95")
    jerk = (smoothness.get("jerk_rms") or {}).get("mean")
    ee_jerk = (smoothness.get("ee_jerk_rms") or {}).get("mean")
    return " / ".join(
        "—" if value is None else f"{value:{spec}}" for value, spec in ((seam, ".3f"), (jerk, ".0f"), (ee_jerk, ".2f"))
    )


def _paired(a: dict[str, Any], b: dict[str, Any]) -> str:
    row = compare_rows(_as_row(a), _as_row(b))
    low, high = row["difference_pp_ci95"]
    discordant = row["discordant"]
    ee_jerk = (row.get("smoothness") or {}).get("ee_jerk_rms")
    measured = (
        ""
        if ee_jerk is None
        else "; end-effector jerk {:+.2f} m/s³ (95 % CI {:+.2f} to {:+.2f})".format(
            ee_jerk["mean_difference"], *ee_jerk["mean_difference_ci95"]
        )
    )
    return (
        f"{row['difference_pp']:+.0f} pp (95 % CI {low:+.0f} to {high:+.0f}), McNemar p {row['mcnemar_p']:.2g} "
        f"({discordant['only_a']} only A, {discordant['only_b']} only B){measured}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--act", type=Path, default=ROOT / "models" / "so101_pick_act")
    parser.add_argument("--act-smooth", type=Path, required=True)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--delays", type=int, nargs="+", default=[0, 1, 2, 4])
    parser.add_argument("--real-time", action="store_true", help="Also a column in real-time mode.")
    args = parser.parse_args()

    act = {"path": str(args.act.absolute()), "device": "cpu", "threads": 1}
    smooth = {"path": str(args.act_smooth.absolute()), "device": "cpu", "threads": 1}
    smooth["accept_licenses"] = ["NOASSERTION"]  # the package declares no licence
    policies = {
        "ACT, stale start": (act, ["executor.indexing=stale_start"]),
        "ACT, tick-indexed": (act, []),
        "act-smooth, tick-indexed + prefix": (smooth, []),
    }
    columns: list[int | str] = [*args.delays, *([REAL_TIME] if args.real_time else [])]
    print(machine_line())
    started = time.perf_counter()
    reports: dict[tuple[str, int | str], dict[str, Any]] = {}
    for name, (params, settings) in policies.items():
        for column in columns:
            measured = column == REAL_TIME
            delay = [] if measured else [f"virtual_latency.ticks={column}"]
            reports[name, column] = _sim_run(params, args.episodes, settings + delay, measured)
            print(f"  {name}, {'real time' if measured else f'd = {column}'}: {_cell(reports[name, column])}")
    print(f"({time.perf_counter() - started:.0f} s, {args.episodes} episodes a cell, seeds from 0)\n")

    heads = [REAL_TIME if c == REAL_TIME else f"d = {c}" for c in columns]
    smooth_head = "seam jump p95 / jerk RMS / end-effector jerk RMS (m/s³), " + " · ".join(heads)
    print("| policy / executor | " + " | ".join(heads) + f" | {smooth_head} |")
    print("|---|" + "---|" * (len(columns) + 1))
    for name in policies:
        cells = [_cell(reports[name, c]) for c in columns]
        smooth_cells = " · ".join(_smooth(reports[name, c]) for c in columns)
        print(f"| {name} | " + " | ".join(cells) + f" | {smooth_cells} |")
    print()
    names = list(policies)
    for column in columns:
        head = REAL_TIME if column == REAL_TIME else f"d = {column}"
        print(f"{head}: tick-indexed − stale start {_paired(reports[names[0], column], reports[names[1], column])}")
        print(f"{head}: act-smooth − ACT tick-indexed {_paired(reports[names[1], column], reports[names[2], column])}")


if __name__ == "__main__":
    main()
