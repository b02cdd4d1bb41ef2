"""What every simulator adapter owes the evaluation loop, checked on each shipped benchmark family.

One env step per tick, outcomes that depend on the seeds alone (however the episodes are sliced,
in worker processes and on Ray), success reported under the scene's key, and a recording that
passes the LeRobot dataset checker with the env's own names.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner

from openral_cli.main import cli
from openral_core import SimEnvironment, TickResult, WorldState
from openral_core.config import load_model_yaml
from openral_dataset.check import check_dataset
from openral_observability.observer import TickObserver
from openral_sim.build import build_sim_runner, run_episodes
from openral_sim.env import make_env
from openral_sim.evaluation import run_units, split_episodes

SCENES = Path(__file__).resolve().parents[2] / "scenes" / "sim"


@dataclass(frozen=True)
class Family:
    scene: str
    expert: str
    module: str
    reason: str


FAMILIES = [
    Family("aloha_transfer_cube.yaml", "aloha_transfer_cube_expert", "gym_aloha", "needs the 'aloha' extra"),
    Family("aloha_insertion.yaml", "aloha_insertion_expert", "gym_aloha", "needs the 'aloha' extra"),
    Family("franka_libero_pnp.yaml", "libero_expert", "libero", "needs the 'libero' extra"),
]


def _scene(family: Family, **update: Any) -> SimEnvironment:
    if importlib.util.find_spec(family.module) is None:
        pytest.skip(family.reason)
    scene = load_model_yaml(SimEnvironment, SCENES / family.scene)
    return scene.model_copy(update={"cameras": [], **update})


class _Ticks(TickObserver):
    def __init__(self) -> None:
        self.ticks: list[TickResult] = []

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        self.ticks.append(tick)

    def close(self) -> None:
        return


@pytest.fixture(params=FAMILIES, ids=lambda f: f.scene.removesuffix(".yaml"))
def family(request: pytest.FixtureRequest) -> Family:
    return request.param  # type: ignore[no-any-return]


def test_one_env_step_per_tick_and_success_under_the_scenes_key(family: Family) -> None:
    runner = build_sim_runner(_scene(family, n_episodes=2), family.expert)
    log = _Ticks()
    runner.observers.append(log)
    runner.skill.configure()
    runner.skill.activate()
    runner.activate()
    try:
        runner.run(max_ticks=10_000)
    finally:
        runner.deactivate()
    assert [e.episode_idx for e in runner.episode_results] == [0, 1]
    for episode in runner.episode_results:
        assert episode.success
        assert episode.ended_by == "success"
        ticks = [t for t in log.ticks if t.episode_idx == episode.episode_idx]
        assert ticks[0].step_idx is None  # the reset tick
        assert [t.step_idx for t in ticks[1:]] == list(range(episode.steps))
        assert all(t.action_applied for t in ticks[1:])
        assert episode.steps_to_success == episode.steps


def test_outcomes_depend_on_the_seeds_alone(family: Family) -> None:
    scene = _scene(family, n_episodes=3, max_steps=60)
    whole = run_episodes(scene, "random").episodes
    tail = run_episodes(scene, "random", first_episode=1, n_episodes=2).episodes
    assert [e.outcome() for e in tail] == [e.outcome() for e in whole[1:]]
    assert len({json.dumps(e.outcome(), sort_keys=True) for e in whole}) == 3  # the seeds differ


@pytest.mark.slow
def test_worker_processes_give_the_outcomes_of_one_process(family: Family) -> None:
    scene = _scene(family, n_episodes=2)
    here = run_units(split_episodes(scene, family.expert, {}, 2, 1)).episodes
    workers = run_units(split_episodes(scene, family.expert, {}, 2, 2), workers=2).episodes
    assert [e.outcome() for e in workers] == [e.outcome() for e in here]


# Under ``uv run`` Ray would start its workers with ``uv run`` in a packaged copy of the project
# (a fresh venv each); they are on this machine and use this interpreter.
RAY_ENV = {**os.environ, "RAY_ENABLE_UV_RUN_RUNTIME_ENV": "0"}

RAY_RUN = """
import json, ray
from openral_core import SimEnvironment
from openral_sim.evaluation import run_units, split_episodes
scene = SimEnvironment.model_validate_json({scene!r})
ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
try:
    batch = run_units(split_episodes(scene, {skill!r}, {{}}, 2, 2), ray_address="local")
finally:
    ray.shutdown()
print(json.dumps([e.outcome() for e in batch.episodes]))
"""


@pytest.mark.slow
@pytest.mark.timeout(600)  # a Ray cluster of its own starts first: tens of seconds on a busy machine
def test_ray_gives_the_outcomes_of_one_process(family: Family) -> None:
    if importlib.util.find_spec("ray") is None:  # not imported here: Ray installs process-wide handlers
        pytest.skip("needs the 'ray' extra")
    scene = _scene(family, n_episodes=2)
    here = run_units(split_episodes(scene, family.expert, {}, 2, 1)).episodes
    code = RAY_RUN.format(scene=scene.model_dump_json(), skill=family.expert)
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=False, env=RAY_ENV
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == [e.outcome() for e in here]


def test_a_recording_passes_the_dataset_checker_with_the_envs_names(family: Family, tmp_path: Path) -> None:
    scene = _scene(family, n_episodes=2)
    camera = load_model_yaml(SimEnvironment, SCENES / family.scene).cameras[0]
    small = camera.model_copy(update={"width": 128, "height": 96})
    scene_file = tmp_path / "scene.yaml"
    scene_file.write_text(yaml.safe_dump(scene.model_copy(update={"cameras": [small]}).model_dump(mode="json")))
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        cli,
        ["sim", "run", "--config", str(scene_file), "--skill", family.expert, "--dataset-out", str(out),
         "--vcodec", "h264"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    report = check_dataset(out)
    assert report.problems == []
    assert report.episodes == 2
    assert report.videos == 2
    info = json.loads((out / "meta" / "info.json").read_text())
    env = make_env(scene)
    spec = env.spec
    env.close()
    assert info["features"]["action"]["names"] == list(spec.action_names)
    assert info["features"]["observation.state"]["names"] == list(spec.state_names)
    assert info["features"][f"observation.images.{small.name}"]["shape"][:2] == [96, 128]
    assert info["fps"] == round(spec.control_hz)
