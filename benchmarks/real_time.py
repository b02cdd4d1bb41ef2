"""Real time vs virtual latency: one policy's success paced by the wall clock, and at virtual delays d = 0..4.

The committed SO-101 pick policy (``onnx_policy`` with ``models/so101_pick_mlp.onnx``) on the same
seeds, once with ``virtual_latency: measured`` (the wall clock paces the steps at the env's control
rate, the model infers on the executor's worker) and once per virtual delay. ``--extra-ms`` adds
that much compute to each inference (a slower model on this machine), so the measured row moves
along the virtual ones. Each row prints its success with the Wilson 95 % interval; the measured row
also its median delay in ticks as the executor measured it, its share of stale or held steps and
its policy commands per second. The measured row's outcomes depend on this machine and its load.

Run:  uv run python benchmarks/real_time.py [--episodes 20] [--extra-ms 0]
      (needs the 'twin' and 'policy' extras; the measured row takes about a minute at 10 Hz)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from statistics import median
from typing import Any

from _common import machine_line
from openral_core import SimEnvironment, VirtualLatency
from openral_rskill.chunks import ChunkRequest
from openral_sim.build import build_sim_runner
from openral_sim.evaluation import summarize, wilson_interval

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
PARAMS = {"model": str(ROOT / "models" / "so101_pick_mlp.onnx")}


def _evaluate(scene: SimEnvironment, extra_s: float) -> tuple[dict[str, Any], list[int]]:
    """The scene's episodes with the policy (each inference ``extra_s`` longer): summary and measured delays."""
    runner = build_sim_runner(scene, "onnx_policy", PARAMS)
    skill = runner.skill
    if extra_s > 0:
        infer = skill._chunk_impl  # the model's own inference, made slower for this run

        def slower(request: ChunkRequest) -> Any:
            started = time.perf_counter()
            rows = infer(request)
            time.sleep(max(0.0, extra_s - (time.perf_counter() - started)))
            return rows

        skill._chunk_impl = slower  # type: ignore[method-assign]
    skill.configure()
    skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=scene.n_episodes * (scene.max_steps + 1) + 1)
    finally:
        runner.deactivate()
        skill.shutdown()
    delays = list(runner.executor.stats.delays_ticks) if runner.executor is not None else []
    return summarize(runner.episode_results), delays


def _line(name: str, summary: dict[str, Any], delays: list[int] | None = None) -> str:
    low, high = wilson_interval(summary["n_success"], summary["n_episodes"])
    text = f"{name:14s} {summary['pc_success']:5.1f} %  [{100 * low:5.1f}, {100 * high:5.1f}]"
    live = summary.get("real_time")
    if delays is not None and live is not None:
        text += (
            f"   measured delay p50 {median(delays) if delays else float('nan'):.0f} ticks, "
            f"{100 * live['stale_or_held_ratio']:.1f} % of steps stale or held, "
            f"{live['commands_per_s']:.1f} policy commands/s, {live['steps_per_s']:.1f} steps/s"
        )
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--extra-ms", type=float, default=0.0, help="Compute added to each inference.")
    parser.add_argument("--max-delay", type=int, default=4, help="Virtual delays 0..this.")
    args = parser.parse_args()
    print(machine_line())
    scene = SimEnvironment.from_yaml(SCENE).model_copy(update={"cameras": [], "n_episodes": args.episodes})
    last_seed = scene.seed + args.episodes - 1
    print(
        f"{scene.name} / onnx_policy ({Path(PARAMS['model']).name}), seeds {scene.seed}-{last_seed}, "
        f"+{args.extra_ms:g} ms per inference; success with its Wilson 95 % interval"
    )
    summary, delays = _evaluate(scene.model_copy(update={"virtual_latency": "measured"}), args.extra_ms / 1e3)
    print(_line("measured", summary, delays))
    for d in range(args.max_delay + 1):
        summary, _ = _evaluate(scene.model_copy(update={"virtual_latency": VirtualLatency(ticks=d)}), 0.0)
        print(_line(f"virtual d={d}", summary))


if __name__ == "__main__":
    main()
