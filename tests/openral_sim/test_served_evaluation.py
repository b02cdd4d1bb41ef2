"""Served evaluation: one policy server, the episodes as its remote_policy clients, the local run's outcomes."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from openral_core import ROSConfigError, SimEnvironment
from openral_remote.admission import ServeLimits
from openral_sim.evaluation import run_units, split_episodes
from openral_sim.served import REMOTE_SKILL, PolicyHost

pytestmark = [pytest.mark.timeout(600), pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
SCENE = SimEnvironment.from_yaml(ROOT / "scenes" / "sim" / "so101_pick.yaml").model_copy(update={"n_episodes": 4})
POLICY = {"model": str(ROOT / "models" / "so101_pick_mlp.onnx")}


def test_served_episodes_have_the_local_outcomes_for_the_same_seeds() -> None:
    assert SCENE.virtual_latency is not None  # a due tick waits for its chunk
    local = run_units(split_episodes(SCENE, "onnx_policy", POLICY, 4, 1)).episodes
    host = PolicyHost(SCENE, "onnx_policy", POLICY, limits=ServeLimits(max_batch=8, max_wait_ms=2.0))
    try:
        units = split_episodes(SCENE, REMOTE_SKILL, host.client_params(), 4, 2)
        served = run_units(units, workers=2).episodes
        stats = host.stats()
    finally:
        host.close()
    assert [e.outcome() for e in served] == [e.outcome() for e in local]
    assert stats["served"] > 4 * 2  # every chunk of every episode came from the server
    assert host.server.clients == 0  # closed: the workers' episodes were let go


def test_a_skill_of_one_row_per_request_cannot_be_served() -> None:
    with pytest.raises(ROSConfigError, match="cannot be served"):
        PolicyHost(SCENE, "so101_pick_expert", {}, limits=ServeLimits())


# Under ``uv run`` Ray would start its workers with ``uv run`` in a packaged copy of the project
# (a fresh venv each); they are on this machine and use this interpreter.
RAY_ENV = {**os.environ, "RAY_ENABLE_UV_RUN_RUNTIME_ENV": "0"}

RAY_RUN = """
import json, ray
from openral_core import SimEnvironment
from openral_remote.admission import ServeLimits
from openral_sim.evaluation import run_units, split_episodes
from openral_sim.served import REMOTE_SKILL, ray_policy_host
scene = SimEnvironment.model_validate_json({scene!r})
ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
try:
    host = ray_policy_host(scene, "onnx_policy", {policy!r}, limits=ServeLimits(max_batch=4), num_gpus=0)
    params = ray.get(host.client_params.remote())
    batch = run_units(split_episodes(scene, REMOTE_SKILL, params, 4, 2), ray_address="local")
    stats = ray.get(host.stats.remote())
    ray.get(host.close.remote())
finally:
    ray.shutdown()
print(json.dumps([[e.outcome() for e in batch.episodes], stats, params["zenoh"]["connect"]]))
"""


def test_on_ray_the_server_is_an_actor_and_the_episodes_are_tasks() -> None:
    if importlib.util.find_spec("ray") is None:  # not imported here: Ray installs process-wide handlers
        pytest.skip("needs the 'ray' extra")
    local = run_units(split_episodes(SCENE, "onnx_policy", POLICY, 4, 1)).episodes
    code = RAY_RUN.format(scene=SCENE.model_dump_json(), policy=POLICY)
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=500, check=False, env=RAY_ENV
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    outcomes, stats, connect = json.loads(proc.stdout.strip().splitlines()[-1])
    assert outcomes == [e.outcome() for e in local]
    assert stats["served"] > 4
    assert connect[0].startswith("tcp/")
    assert not connect[0].startswith("tcp/0.0.0.0")  # the node's address, which other nodes can reach


def test_a_chunk_policys_episode_has_the_outcome_of_its_seed_whatever_ran_before_it() -> None:
    # The chunk executor's latency estimate starts afresh in each simulated episode: run alone or
    # after others in the same process, episode i plays out the same.
    together = run_units(split_episodes(SCENE, "onnx_policy", POLICY, 4, 1)).episodes
    apart = run_units(split_episodes(SCENE, "onnx_policy", POLICY, 4, 4)).episodes
    alone = [run_units([unit]).episodes[0] for unit in split_episodes(SCENE, "onnx_policy", POLICY, 4, 4)]
    assert [e.outcome() for e in together] == [e.outcome() for e in apart] == [e.outcome() for e in alone]
