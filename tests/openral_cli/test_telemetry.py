"""openral deploy exports its run over OTLP: every tick under the command's span, flushed on every exit."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from openral_observability import semconv
from openral_observability.testing import OTLPReceiver

NULL_DEPLOYMENT = """
name: otel_probe
rate_hz: 200
hal: {robot_id: so101_follower, adapter: null}
vla: {id: noop}
safety: {client: envelope}
"""
PARENT_TRACE = "0af7651916cd43dd8448eb211c80319c"
PARENT_SPAN = "b7ad6b7169203331"


def deploy(
    tmp_path: Path, *args: str, env: dict[str, str] | None = None, text: str = NULL_DEPLOYMENT
) -> subprocess.Popen[str]:
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    base = {k: v for k, v in os.environ.items() if not k.startswith("OTEL_") and k != "TRACEPARENT"}
    return subprocess.Popen(
        [sys.executable, "-m", "openral_cli", "deploy", "--config", str(path), "--json", *args],
        env={**base, **(env or {})},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    stdout, stderr = proc.communicate(timeout=60)
    return proc.returncode, stdout, stderr


def test_ticks_are_exported_under_the_cli_command_span(tmp_path: Path) -> None:
    with OTLPReceiver() as receiver:
        code, stdout, stderr = finish(deploy(tmp_path, "--max-ticks", "20", "--otlp-endpoint", receiver.endpoint))
        assert code == 0, stderr
        result = json.loads(stdout)
        spans = receiver.spans()
    (root,) = [s for s in spans if s.name == semconv.SPAN_CLI_COMMAND]
    assert root.parent_span_id == b""  # the root of the run's trace
    attributes = {kv.key: kv.value for kv in root.attributes}
    assert attributes[semconv.ATTR_CLI_COMMAND].string_value == "deploy"
    assert attributes[semconv.ATTR_RUN_TICKS].int_value == 20
    ticks = [s for s in spans if s.name == semconv.SPAN_TICK]
    assert len(ticks) == 20
    assert {t.parent_span_id for t in ticks} == {root.span_id}
    assert {t.trace_id for t in ticks} == {root.trace_id}
    assert result["trace_id"] == root.trace_id.hex()
    # Phases hang under their tick.
    tick_ids = {t.span_id for t in ticks}
    sends = [s for s in spans if s.name == semconv.SPAN_HAL_SEND_ACTION]
    assert len(sends) == 20
    assert {s.parent_span_id for s in sends} == tick_ids
    assert any(m.name == semconv.METRIC_TICK_DURATION for m in receiver.metrics())
    assert receiver.resource_attributes()["service.name"] == "openral"


def test_environment_configures_export_and_traceparent_continues_a_trace(tmp_path: Path) -> None:
    with OTLPReceiver() as receiver:
        env = {
            "OTEL_EXPORTER_OTLP_ENDPOINT": receiver.endpoint,
            "TRACEPARENT": f"00-{PARENT_TRACE}-{PARENT_SPAN}-01",
        }
        code, stdout, stderr = finish(deploy(tmp_path, "--max-ticks", "5", env=env))
        assert code == 0, stderr
        spans = receiver.spans()
    (root,) = [s for s in spans if s.name == semconv.SPAN_CLI_COMMAND]
    assert (root.trace_id.hex(), root.parent_span_id.hex()) == (PARENT_TRACE, PARENT_SPAN)
    assert json.loads(stdout)["trace_id"] == PARENT_TRACE
    assert len([s for s in spans if s.name == semconv.SPAN_TICK]) == 5


def test_a_zero_sample_ratio_exports_metrics_but_no_spans(tmp_path: Path) -> None:
    with OTLPReceiver() as receiver:
        args = ("--max-ticks", "5", "--otlp-endpoint", receiver.endpoint, "--trace-sample-ratio", "0")
        code, stdout, stderr = finish(deploy(tmp_path, *args))
        assert code == 0, stderr
        assert receiver.spans() == []
        assert any(m.name == semconv.METRIC_TICK_DURATION for m in receiver.metrics())
    assert len(json.loads(stdout)["trace_id"]) == 32  # the run still has a trace id to quote


def test_sigint_flushes_the_whole_trace(tmp_path: Path) -> None:
    with OTLPReceiver() as receiver:
        proc = deploy(tmp_path, "--otlp-endpoint", receiver.endpoint)
        # The batch processor exports ticks while running; wait for the first ones, then interrupt.
        assert receiver.wait_for(lambda r: any(s.name == semconv.SPAN_TICK for s in r.spans()), timeout_s=30)
        proc.send_signal(signal.SIGINT)
        code, stdout, stderr = finish(proc)
        assert code == 130, stderr
        result = json.loads(stdout)
        spans = receiver.spans()
    (root,) = [s for s in spans if s.name == semconv.SPAN_CLI_COMMAND]  # ends last: only a flush on exit sends it
    attributes = {kv.key: kv.value for kv in root.attributes}
    assert attributes[semconv.ATTR_RUN_STOP_REASON].string_value == "signal:SIGINT"
    assert len([s for s in spans if s.name == semconv.SPAN_TICK]) == result["n_ticks"]


def test_a_config_error_is_exported_as_a_failed_command(tmp_path: Path) -> None:
    with OTLPReceiver() as receiver:
        bad = "hal: {robot_id: so101_follower}\nvla: {id: helo}\n"
        code, _stdout, stderr = finish(deploy(tmp_path, "--otlp-endpoint", receiver.endpoint, text=bad))
        assert code == 2, stderr
        spans = receiver.spans()
    (root,) = [s for s in spans if s.name == semconv.SPAN_CLI_COMMAND]
    assert root.status.code == root.status.STATUS_CODE_ERROR
    assert any(event.name == "exception" for event in root.events)


def test_export_without_the_otel_extra_names_it(tmp_path: Path) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(NULL_DEPLOYMENT)
    code = (
        "import sys\n"
        "sys.modules['opentelemetry.sdk'] = None\n"
        "from openral_cli.main import main\n"
        "sys.argv = ['openral', 'deploy', '--config', sys.argv[1], '--otlp-endpoint', 'http://127.0.0.1:9']\n"
        "main()\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=60, check=False
    )
    assert proc.returncode == 2, proc.stderr
    assert "openral[otel]" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_status_goes_to_stderr_and_stdout_stays_json(tmp_path: Path) -> None:
    started = time.monotonic()
    code, stdout, stderr = finish(deploy(tmp_path, "--duration", "5.6"))
    assert code == 0, stderr
    assert time.monotonic() - started >= 5.6
    json.loads(stdout)
    assert "tick p50" in stderr  # one plain status line every 5 s when stderr is not a terminal


def test_log_lines_become_log_records_in_the_command_span(tmp_path: Path) -> None:
    unchecked = NULL_DEPLOYMENT.replace("{client: envelope}", "{client: null}")  # warns while building
    with OTLPReceiver() as receiver:
        code, _stdout, stderr = finish(
            deploy(tmp_path, "--max-ticks", "3", "--otlp-endpoint", receiver.endpoint, text=unchecked)
        )
        assert code == 0, stderr
        spans, logs = receiver.spans(), receiver.logs()
    (root,) = [s for s in spans if s.name == semconv.SPAN_CLI_COMMAND]
    (record,) = [r for r in logs if "safety checking is disabled" in r.body.string_value]
    assert record.severity_text == "WARN"
    assert (record.trace_id, record.span_id) == (root.trace_id, root.span_id)
    assert f"trace_id={root.trace_id.hex()}" in stderr  # the console line carries the ids too


def test_group_ctrl_c_through_uv_with_otlp_export_still_flushes_and_exits_130(tmp_path: Path, deploy_process) -> None:
    path = tmp_path / "robot.yaml"
    path.write_text(NULL_DEPLOYMENT)
    with OTLPReceiver() as receiver:
        proc = deploy_process(
            ["deploy", "--config", str(path), "--json", "--otlp-endpoint", receiver.endpoint], through_uv=True
        )
        assert receiver.wait_for(lambda r: any(s.name == semconv.SPAN_TICK for s in r.spans()), timeout_s=60)
        proc.signal_group(signal.SIGINT)  # a terminal's Ctrl-C: uv and openral both get it, uv forwards a copy
        proc.wait_for("SIGINT: stopping after this tick")
        time.sleep(0.4)
        proc.signal_group(signal.SIGINT)  # pressed again while telemetry is being flushed
        code, stdout = proc.finish(timeout=60)
        assert code == 130, proc.stderr
        assert "Aborted" not in proc.stderr
        result = json.loads(stdout)
        assert receiver.wait_for(lambda r: any(s.name == semconv.SPAN_CLI_COMMAND for s in r.spans()), timeout_s=10), (
            "the command span, exported last, arrived"
        )
        spans = receiver.spans()
    assert len([s for s in spans if s.name == semconv.SPAN_TICK]) == result["n_ticks"]
