"""The twin's camera deployments on a busy machine: stale reads, render cost and delivered fps.

Runs each deployment through the real ``openral deploy --json`` for ``--ticks`` ticks while
``--hogs`` CPU-bound processes (default: one per core) spin beside it, ``--rounds`` times, once
with the render meshes simplified (the default) and once with the full meshes
(``backend_params.mesh_cell_mm: 0``), so the two compare within one sitting. A run that fails its
start (no fresh frame in time) is counted as such, with its one-line reason.

    uv run python benchmarks/twin_camera_load.py
    uv run python benchmarks/twin_camera_load.py --deployments so101_twin_camera --rounds 5 --hogs 0
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml

from _common import machine_line

ROOT = Path(__file__).resolve().parents[1]
DEPLOYMENTS = ROOT / "deployments"


def _spin() -> None:
    while True:
        pass


def _variant(name: str, cell_mm: float | None, folder: Path) -> Path:
    """The deployment ``name`` with its camera's mesh cell set (``None``: as shipped), failures never stopping it."""
    config = yaml.safe_load((DEPLOYMENTS / f"{name}.yaml").read_text())
    for sensor in config.get("sensors", []):
        if cell_mm is not None:
            sensor.setdefault("backend_params", {})["mesh_cell_mm"] = cell_mm
    # Count every stale read instead of stopping after five in a row.
    config.setdefault("faults", {})["max_consecutive_failures"] = 1_000_000
    for observer in config.get("observers", []):  # model paths are relative to the shipped file
        model = observer.get("params", {})
        for detector in model.get("detectors", []):
            params = detector.get("params", {})
            if "model" in params:
                params["model"] = str((DEPLOYMENTS / params["model"]).resolve())
    path = folder / f"{name}_{'shipped' if cell_mm is None else cell_mm}.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def _run(config: Path, ticks: int) -> dict[str, Any]:
    done = subprocess.run(
        [sys.executable, "-m", "openral_cli", "deploy", "--config", str(config), "--max-ticks", str(ticks), "--json"],
        check=False,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
    )
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
        return {"failed": last}
    result = json.loads(done.stdout)
    sensor = next(iter(result["metadata"]["sensors"].values()))
    return {
        "ticks": result["n_ticks"],
        "stale": result["stale_reads"],
        "render_ms": sensor.get("render_ms"),
        "fps": sensor.get("delivered_fps"),
        "triangles": sensor.get("triangles"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--deployments", nargs="+", default=["so101_twin_camera", "so101_twin_perception"])
    parser.add_argument("--ticks", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--hogs", type=int, default=os.cpu_count() or 1, help="CPU-bound processes beside the run")
    args = parser.parse_args()

    hogs = [multiprocessing.Process(target=_spin, daemon=True) for _ in range(args.hogs)]
    for hog in hogs:
        hog.start()
    try:
        print(machine_line())
        print(f"{args.hogs} CPU-bound process(es) beside each run; {args.ticks} ticks at 30 Hz; {args.rounds} rounds")
        print(
            f"{'deployment':24} {'meshes':10} {'triangles':>9} {'stale reads (each round)':>28} "
            f"{'render ms p50':>13} {'fps p50':>8}  failed starts"
        )
        with tempfile.TemporaryDirectory() as folder:
            for name in args.deployments:
                for label, cell in (("simplified", None), ("full", 0.0)):
                    config = _variant(name, cell, Path(folder))
                    runs = [_run(config, args.ticks) for _ in range(args.rounds)]
                    ok = [r for r in runs if "failed" not in r]
                    failed = [r["failed"] for r in runs if "failed" in r]
                    stale = ", ".join(f"{r['stale']}/{r['ticks']}" for r in ok) or "-"
                    render = statistics.median(r["render_ms"] for r in ok) if ok else float("nan")
                    fps = statistics.median(r["fps"] for r in ok) if ok else float("nan")
                    triangles = ok[0]["triangles"] if ok else "-"
                    print(f"{name:24} {label:10} {triangles:>9} {stale:>28} {render:13.1f} {fps:8.1f}  {len(failed)}")
                    for reason in failed:
                        print(f"    failed start: {reason}")
        print(machine_line())
    finally:
        for hog in hogs:
            hog.terminate()


if __name__ == "__main__":
    main()
