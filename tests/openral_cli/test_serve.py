"""``openral serve`` and a simulated robot on ``remote_policy``: the outcomes of the local policy, in one trace."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from openral_observability import semconv
from openral_observability.testing import OTLPReceiver
from openral_remote.testing import free_endpoint

pytestmark = pytest.mark.timeout(300)

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "scenes" / "sim" / "so101_pick.yaml"
MODEL = {"model": str(ROOT / "models" / "so101_pick_mlp.onnx")}
EPISODES = "3"


def _openral(*args: str) -> list[str]:
    return [sys.executable, "-m", "openral_cli", *args]


@pytest.fixture(scope="module")
def receiver() -> Iterator[OTLPReceiver]:
    with OTLPReceiver() as otlp:
        yield otlp


@pytest.fixture(scope="module")
def served(receiver: OTLPReceiver) -> Iterator[str]:
    endpoint = free_endpoint()
    server = subprocess.Popen(
        _openral(
            "serve",
            "--skill",
            "onnx_policy",
            "--skill-params",
            json.dumps(MODEL),
            "--scene",
            str(SCENE),
            "--listen",
            endpoint,
            "--otlp-endpoint",
            receiver.endpoint,
        ),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        yield endpoint
    finally:
        server.send_signal(signal.SIGINT)
        _out, err = server.communicate(timeout=60)
        assert server.returncode == 0, err
        assert "served " in err  # its closing summary


def _sim(skill: str, params: dict[str, object], *extra: str) -> dict[str, object]:
    done = subprocess.run(
        _openral(
            "sim",
            "run",
            "--config",
            str(SCENE),
            "--skill",
            skill,
            "--skill-params",
            json.dumps(params),
            "--n-episodes",
            EPISODES,
            "--json",
            *extra,
        ),
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, object] = json.loads(done.stdout)
    return result


def test_a_served_policy_gives_the_robot_what_the_local_one_would_in_one_trace(served, receiver):
    remote_params = {"policy": "onnx_policy", "zenoh": {"connect": [served]}}
    remote = _sim("remote_policy", remote_params, "--otlp-endpoint", receiver.endpoint)
    local = _sim("onnx_policy", MODEL)
    assert [e["success"] for e in remote["episodes"]] == [e["success"] for e in local["episodes"]]
    assert [e["steps"] for e in remote["episodes"]] == [e["steps"] for e in local["episodes"]]

    def has_server_span(r: OTLPReceiver) -> bool:
        return any(s.name == semconv.SPAN_REMOTE_INFER for s in r.spans())

    assert receiver.wait_for(has_server_span, timeout_s=30)
    spans = receiver.spans()
    by_id = {span.span_id: span for span in spans}
    chains = 0
    for infer in (s for s in spans if s.name == semconv.SPAN_REMOTE_INFER):
        names, span = [], infer
        while span.parent_span_id and span.parent_span_id in by_id:
            assert by_id[span.parent_span_id].trace_id == infer.trace_id
            span = by_id[span.parent_span_id]
            names.append(span.name)
        if names[:3] == [semconv.SPAN_REMOTE_REQUEST, semconv.SPAN_EXECUTOR_CHUNK, semconv.SPAN_TICK]:
            chains += 1
    assert chains >= 1, "no server inference span under a robot tick"


def test_the_shipped_remote_deployment_runs_the_twin_on_a_served_chunking_policy(tmp_path: Path):
    import yaml  # noqa: PLC0415

    endpoint = free_endpoint()
    deployment = yaml.safe_load((ROOT / "deployments" / "so101_twin_remote.yaml").read_text(encoding="utf-8"))
    deployment["vla"]["params"]["zenoh"]["connect"] = [endpoint]
    path = tmp_path / "remote.yaml"
    path.write_text(yaml.safe_dump(deployment), encoding="utf-8")
    server = subprocess.Popen(
        _openral(
            "serve",
            "--skill",
            "hello",
            "--skill-params",
            '{"chunk_size": 15}',
            "--robot",
            "so101_follower",
            "--name",
            deployment["vla"]["params"]["policy"],
            "--listen",
            endpoint,
        ),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        done = subprocess.run(
            _openral("deploy", "--config", str(path), "--max-ticks", "90", "--json"),
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
    finally:
        server.send_signal(signal.SIGINT)
        server.communicate(timeout=60)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["stop_reason"] == "max_ticks"
    executor = result["metadata"]["executor"]
    assert executor["chunks_used"] >= 3
    assert executor["unavailable_ticks"] == 0


def test_a_wrong_remote_setting_names_the_field(tmp_path: Path):
    import yaml  # noqa: PLC0415

    deployment = yaml.safe_load((ROOT / "deployments" / "so101_twin_remote.yaml").read_text(encoding="utf-8"))
    deployment["vla"]["params"]["zenoh"]["lease"] = 1000  # lease_ms is the key
    path = tmp_path / "remote.yaml"
    path.write_text(yaml.safe_dump(deployment), encoding="utf-8")
    done = subprocess.run(_openral("validate", str(path)), capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert "zenoh.lease" in done.stderr
    assert "lease_ms" in done.stderr
