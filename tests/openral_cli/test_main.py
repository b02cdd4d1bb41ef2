"""The openral command: exit codes, one clear line for bad config, JSON on stdout only."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from openral_cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
TWIN = ROOT / "deployments" / "so101_twin_hello.yaml"

NULL_DEPLOYMENT = """
name: null_bench
rate_hz: 200
hal: {robot_id: so101_follower, adapter: null}
vla: {id: noop}
safety: {client: envelope}
"""


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "robot.yaml"
    path.write_text(text)
    return path


def test_deploy_json_prints_only_the_run_result(tmp_path: Path) -> None:
    path = write(tmp_path, NULL_DEPLOYMENT)
    proc = subprocess.run(
        [sys.executable, "-m", "openral_cli", "deploy", "--config", str(path), "--max-ticks", "40", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["n_ticks"] == 40
    assert result["stop_reason"] == "max_ticks"
    assert result["rate_hz"] == 200
    # An absolute schedule never runs faster than its rate, whatever the load.
    assert 0 < result["effective_rate_hz"] <= 200 * 1.001


def test_deploy_human_summary(tmp_path: Path) -> None:
    path = write(tmp_path, NULL_DEPLOYMENT)
    out = CliRunner().invoke(cli, ["deploy", "--config", str(path), "--duration", "0.1"])
    assert out.exit_code == 0, out.output
    assert "stopped: duration" in out.output
    assert "achieved" in out.output


@pytest.mark.parametrize(
    ("text", "field", "fix"),
    [
        ("hal: {robot_id: so101_follower}\nvla: {id: helo}\n", "vla.id", "did you mean 'hello'"),
        (
            "hal: {robot_id: so101_follower}\nvla: {id: hello}\nrate_hz: 30\nsensors: [{sensor_id: a, fpss: 3}]\n",
            "sensors[0].fpss",
            "did you mean 'fps'",
        ),
        ("hal: {robot_id: so101_folower}\nvla: {id: hello}\n", "hal.robot_id", "so101_follower"),
        ("hal: {robot_id: so101_follower}\nvla: {id: hello}\nrate_hz: -3\n", "rate_hz", "greater than 0"),
        ("hal: {robot_id: so101_follower}\n", "vla", "missing"),
    ],
)
def test_bad_config_exits_2_with_one_line_naming_field_and_fix(tmp_path: Path, text: str, field: str, fix: str) -> None:
    path = write(tmp_path, text)
    for command in (["validate", str(path)], ["deploy", "--config", str(path), "--max-ticks", "1"]):
        out = CliRunner().invoke(cli, command)
        assert out.exit_code == 2, out.output
        lines = [line for line in out.output.splitlines() if line.strip()]
        assert len(lines) == 1, out.output
        assert field in lines[0]
        assert fix in lines[0]
        assert "Traceback" not in out.output


def test_debug_shows_traceback(tmp_path: Path) -> None:
    path = write(tmp_path, "hal: {robot_id: so101_follower}\nvla: {id: helo}\n")
    out = CliRunner().invoke(cli, ["--debug", "validate", str(path)])
    assert out.exit_code == 2
    assert "Traceback" in out.output


def test_missing_file_is_a_config_error(tmp_path: Path) -> None:
    out = CliRunner().invoke(cli, ["validate", str(tmp_path / "nope.yaml")])
    assert out.exit_code == 2
    assert "not found" in out.output


def test_validate_accepts_the_shipped_twin_deployment() -> None:
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    out = CliRunner().invoke(cli, ["validate", str(TWIN)])
    assert out.exit_code == 0, out.output
    assert "so101_follower" in out.output


def _listening_socket() -> socket.socket:
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    listener.setblocking(False)
    return listener


def _was_contacted(listener: socket.socket) -> bool:
    try:
        conn, _ = listener.accept()
    except BlockingIOError:
        return False
    conn.close()
    return True


def test_validate_of_a_remote_deployment_neither_waits_for_nor_contacts_the_server(tmp_path: Path) -> None:
    pytest.importorskip("zenoh", reason="needs the 'remote' extra")
    with _listening_socket() as server:  # where the file says the server is: it must never be called
        port = server.getsockname()[1]
        text = (ROOT / "deployments" / "so101_twin_remote.yaml").read_text(encoding="utf-8")
        text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}").replace(
            "connect_timeout_s: 10", "connect_timeout_s: 600"
        )
        path = write(tmp_path, text)
        out = CliRunner().invoke(cli, ["validate", str(path)])
        assert out.exit_code == 0, out.output
        assert "remote_policy" in out.output
        assert not _was_contacted(server)
        bad = CliRunner().invoke(
            cli, ["validate", str(write(tmp_path, text.replace("deadline_ms: 300", "deadline_ms: -1")))]
        )
        assert bad.exit_code == 2, bad.output
        assert "vla.params.deadline_ms" in bad.output


def test_validate_of_a_perception_deployment_binds_nothing(tmp_path: Path) -> None:
    pytest.importorskip("zenoh", reason="needs the 'remote' extra")
    pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
    pytest.importorskip("mujoco", reason="needs the 'twin' extra")
    with _listening_socket() as taken:  # the port the file listens on is in use: validate must not care
        port = taken.getsockname()[1]
        text = (ROOT / "deployments" / "so101_twin_perception.yaml").read_text(encoding="utf-8")
        text = text.replace("tcp/127.0.0.1:7448", f"tcp/127.0.0.1:{port}").replace("../models/", f"{ROOT}/models/")
        path = write(tmp_path, text)
        for _ in range(2):
            out = CliRunner().invoke(cli, ["validate", str(path)])
            assert out.exit_code == 0, out.output


def test_validate_refuses_a_model_path_that_cannot_be_a_file(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime", reason="needs the 'policy' extra")
    text = (ROOT / "deployments" / "so101_twin_perception.yaml").read_text(encoding="utf-8")
    path = write(tmp_path, text.replace("../models/cube_detector.onnx", "m" * 300 + ".onnx"))
    out = CliRunner().invoke(cli, ["validate", str(path)])
    assert out.exit_code == 2, out.output
    assert "detectors[2].params.model" in out.output
    assert "File name too long" in out.output
    assert "unexpected" not in out.output


def test_validate_creates_no_bag_so_the_deployment_still_runs(tmp_path: Path) -> None:
    pytest.importorskip("mcap", reason="needs the 'dataset' extra")
    path = write(tmp_path, NULL_DEPLOYMENT + "observers:\n  - id: ros2_bag\n    params: {path: run.mcap}\n")
    assert CliRunner().invoke(cli, ["validate", str(path)]).exit_code == 0
    assert not (tmp_path / "run.mcap").exists()
    out = CliRunner().invoke(cli, ["deploy", "--config", str(path), "--max-ticks", "5", "--json"])
    assert out.exit_code == 0, out.output
    assert (tmp_path / "run.mcap").stat().st_size > 0


def test_schema_is_json_schema_of_the_deployment(tmp_path: Path) -> None:
    out = CliRunner().invoke(cli, ["schema"])
    assert out.exit_code == 0
    schema = json.loads(out.output)
    assert schema["title"] == "RobotEnvironment"
    assert {"hal", "vla"} <= set(schema["required"])
    target = tmp_path / "schema.json"
    assert CliRunner().invoke(cli, ["schema", "-o", str(target)]).exit_code == 0
    assert json.loads(target.read_text()) == schema


def test_sigint_finishes_the_tick_and_exits_130(tmp_path: Path, deploy_process) -> None:
    path = write(tmp_path, NULL_DEPLOYMENT)
    proc = deploy_process(["deploy", "--config", str(path), "--json"])
    proc.wait_for("] running")
    proc.signal_group(signal.SIGINT)
    code, stdout = proc.finish(timeout=30)
    assert code == 130, proc.stderr
    result = json.loads(stdout)
    assert result["stop_reason"] == "signal:SIGINT"
    assert "Traceback" not in proc.stderr


def test_deploy_json_on_a_raise_deadline_stop_prints_the_partial_run(tmp_path: Path) -> None:
    # 10 kHz with a 1-tick budget under "raise": the first late tick stops the run.
    text = NULL_DEPLOYMENT.replace("rate_hz: 200", "rate_hz: 10000\ndeadline_overrun_policy: raise")
    path = write(tmp_path, text)
    proc = subprocess.run(
        [sys.executable, "-m", "openral_cli", "deploy", "--config", str(path), "--max-ticks", "100000", "--json"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 1, proc.stderr
    result = json.loads(proc.stdout)
    assert result["stop_reason"] == "deadline"
    assert result["deadline_misses"] >= 1
    assert result["n_ticks"] >= 1
    assert proc.stderr.count("error: ROSDeadlineMissed") == 1


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0", "abc"])
def test_duration_must_be_a_positive_finite_number(tmp_path: Path, value: str) -> None:
    path = write(tmp_path, NULL_DEPLOYMENT)
    out = CliRunner().invoke(cli, ["deploy", "--config", str(path), "--duration", value])
    assert out.exit_code == 2
    assert "--duration" in out.output


def test_deploy_records_a_ros2_bag_with_one_tick_message_per_tick(tmp_path: Path, check_bag) -> None:
    path = write(tmp_path, NULL_DEPLOYMENT)
    recording = tmp_path / "run.mcap"
    out = CliRunner().invoke(cli, ["deploy", "--config", str(path), "--max-ticks", "25", "--mcap", str(recording)])
    assert out.exit_code == 0, out.output
    check_bag(recording, ticks=25)


def test_deploy_foxglove_serves_the_run_and_attaches_the_deployment_to_a_bag(
    tmp_path: Path, check_bag, check_foxglove_served
) -> None:
    path = write(tmp_path, NULL_DEPLOYMENT)
    recording = tmp_path / "run.mcap"
    args = ["deploy", "--config", str(path), "--max-ticks", "10", "--foxglove", "0", "--mcap", str(recording)]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 0, out.output
    check_foxglove_served(out.output)
    check_bag(recording, ticks=10, attached=[path.name])


def test_a_taken_dataset_folder_is_refused_naming_the_flag_and_left_as_it_was(tmp_path: Path) -> None:
    pytest.importorskip("pyarrow", reason="needs the 'dataset' extra")
    path = write(tmp_path, NULL_DEPLOYMENT)
    taken = tmp_path / "taken"
    (taken / "meta").mkdir(parents=True)
    (taken / "meta" / "notes.txt").write_text("mine")
    out = CliRunner().invoke(cli, ["deploy", "--config", str(path), "--max-ticks", "5", "--dataset-out", str(taken)])
    assert out.exit_code == 2, out.output
    assert "--dataset-out" in out.output
    assert "running" not in out.output, "refused while starting, before the first tick"
    assert (taken / "meta" / "notes.txt").read_text() == "mine"
    assert sorted(p.name for p in taken.iterdir()) == ["meta"]


def test_calibrate_records_the_ranges_a_person_moves_through(tmp_path: Path) -> None:
    pytest.importorskip("serial", reason="needs the 'serial' extra (pyserial)")
    import threading  # noqa: PLC0415

    from openral_hal.feetech import protocol as p  # noqa: PLC0415
    from openral_hal.feetech.calibration import load_calibration  # noqa: PLC0415
    from openral_hal.feetech.emulator import ServoBusEmulator  # noqa: PLC0415

    output = tmp_path / "so101.json"
    with ServoBusEmulator(range(1, 7)) as bus:
        done = threading.Event()
        reads = threading.Condition()
        position_reads = [0]

        def on_request(packet: p.Packet) -> None:
            if packet.code == p.Instruction.SYNC_READ and packet.params[0] == p.Register.PRESENT_POSITION:
                with reads:
                    position_reads[0] += 1
                    reads.notify_all()

        def wait_for_reads(more: int) -> None:
            """Wait until ``more`` position reads are requested after now (the first of them sees the arm as it is)."""
            with reads:
                target = position_reads[0] + more
                assert reads.wait_for(lambda: position_reads[0] >= target, timeout=30), "calibrate stopped reading"

        bus.on_request = on_request

        def person_moves_the_arm() -> None:
            # Once the middle pose has been read (a second read is asked for only after the first), sweep
            # each joint 600 ticks each way, as a hand would, holding each end until calibrate has read it.
            wait_for_reads(2)
            for servo_id in range(1, 7):
                bus.move_by_hand(servo_id, 2048 - 600)
                wait_for_reads(1)
                bus.move_by_hand(servo_id, 2048 + 600)
                wait_for_reads(1)
            done.set()

        mover = threading.Thread(target=person_moves_the_arm)
        mover.start()
        out = CliRunner().invoke(
            cli, ["calibrate", "--port", bus.port, "--output", str(output), "--record-s", "1.5"], input="\n\n\n"
        )
        mover.join()
    assert done.is_set()
    assert out.exit_code == 0, out.output
    calibration = load_calibration(output)
    for joint in calibration.joints.values():
        assert joint.range_min <= 2048 - 600
        assert joint.range_max >= 2048 + 600


def test_calibrate_rejects_unknown_joint(tmp_path: Path) -> None:
    args = ["calibrate", "--port", "/dev/null", "-o", str(tmp_path / "c.json"), "--invert", "elbow"]
    out = CliRunner().invoke(cli, args)
    assert out.exit_code == 2
    assert "--invert" in out.output
    assert "elbow_flex" in out.output


@pytest.mark.parametrize(
    ("reason", "code"),
    [
        ("max_ticks", 0),
        ("duration", 0),
        ("skill_done", 0),
        ("terminated", 0),
        ("faults", 1),
        ("estop", 1),
        ("signal:SIGINT", 130),
        ("signal:SIGTERM", 143),
    ],
)
def test_stop_reasons_map_to_exit_codes(reason: str, code: int) -> None:
    from openral_cli.command_lifecycle import exit_code  # noqa: PLC0415
    from openral_core import StopReason  # noqa: PLC0415

    assert exit_code(StopReason(reason)) == code


def test_validate_refuses_a_missing_video_file_that_deploy_would_fail_on(tmp_path: Path) -> None:
    pytest.importorskip("cv2", reason="needs the 'opencv' extra")
    text = NULL_DEPLOYMENT + (
        "sensors:\n  - {sensor_id: front, backend: opencv_thread, backend_params: {device: clips/missing.mp4}}\n"
    )
    out = CliRunner().invoke(cli, ["validate", str(write(tmp_path, text))])
    assert out.exit_code == 2
    assert "sensors[front].backend_params.device: video file not found" in out.output
    assert str(tmp_path / "clips" / "missing.mp4") in out.output, "relative to the deployment's folder"


def test_a_skill_that_finds_its_configuration_wrong_at_configure_exits_2(tmp_path: Path) -> None:
    try:
        import torch  # noqa: PLC0415

        if torch.cuda.is_available():
            pytest.skip("this machine has CUDA: the refusal cannot happen here")
    except ImportError:
        pass  # no PyTorch: refused for that, as a configuration error too
    path = write(
        tmp_path, NULL_DEPLOYMENT.replace("vla: {id: noop}", "vla: {id: gpu_passthrough, params: {device: cuda}}")
    )
    out = CliRunner().invoke(cli, ["deploy", "--config", str(path), "--max-ticks", "3"])
    assert out.exit_code == 2, out.output
    errors = [line for line in out.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, out.output
    assert "cuda" in errors[0] or "torch" in errors[0]
