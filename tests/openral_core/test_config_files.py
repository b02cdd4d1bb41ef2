"""Files a user names are read without trusting them: regular, bounded, UTF-8, plain YAML; one-line errors."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from openral_core import RobotEnvironment, ROSConfigError
from openral_core.config_files import (
    MAX_CONFIG_BYTES,
    MAX_VALUES,
    expand_user_path,
    is_regular_file,
    load_config_file,
    parse_config_text,
    read_config_file,
    require_user_file,
    resolve_user_path,
)

MINIMAL = "hal:\n  robot_id: so101_follower\nvla:\n  id: hello\n"


def _error(call) -> ROSConfigError:
    with pytest.raises(ROSConfigError) as info:
        call()
    assert "\n" not in str(info.value), "every config error is one line"
    return info.value


def _finishes_quickly(call, seconds: float = 10.0) -> object:
    """Run ``call`` on a thread and fail the test if it has not returned within ``seconds``."""
    outcome: list[object] = []
    thread = threading.Thread(target=lambda: outcome.append(_capture(call)), daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"did not return within {seconds} s"
    return outcome[0]


def _capture(call) -> object:
    try:
        return call()
    except Exception as exc:  # returned for inspection
        return exc


def test_fifo_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "deploy.yaml"
    os.mkfifo(fifo)
    outcome = _finishes_quickly(lambda: RobotEnvironment.from_yaml(fifo))
    assert isinstance(outcome, ROSConfigError)
    assert "FIFO" in str(outcome)
    assert "not a regular file" in str(outcome)


def test_tty_is_refused_without_blocking() -> None:
    master, slave = os.openpty()
    try:
        tty = os.ttyname(slave)
        outcome = _finishes_quickly(lambda: read_config_file(tty, field="hal.params.calibration"))
    finally:
        os.close(master)
        os.close(slave)
    assert isinstance(outcome, ROSConfigError)
    assert str(outcome).startswith("hal.params.calibration: ")
    assert "character device" in str(outcome)


def test_dev_zero_is_refused_before_reading() -> None:
    error = _error(lambda: read_config_file("/dev/zero", field="vla.manifest"))
    assert error.field == "vla.manifest"
    assert "character device" in str(error)


def test_directory_is_refused(tmp_path: Path) -> None:
    assert "a directory" in str(_error(lambda: read_config_file(tmp_path)))


def test_oversized_file_is_refused(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_bytes(b"#" * (MAX_CONFIG_BYTES + 1))
    error = _error(lambda: read_config_file(big, field="--config"))
    assert "refused" in str(error)
    assert error.field == "--config"


def test_file_growing_past_the_limit_is_refused_even_when_stat_says_small() -> None:
    # /proc files report size 0 but have content: the read itself is bounded.
    text = read_config_file("/proc/self/status", max_bytes=1 << 16)
    assert "Pid:" in text
    error = _error(lambda: read_config_file("/proc/self/status", max_bytes=16))
    assert "over 16 bytes" in str(error)


def test_utf16_is_named_and_utf8_bom_is_accepted(tmp_path: Path) -> None:
    utf16 = tmp_path / "utf16.yaml"
    utf16.write_text(MINIMAL, encoding="utf-16")
    error = _error(lambda: RobotEnvironment.from_yaml(utf16))
    assert "UTF-16" in str(error)
    assert error.hint == "save it as UTF-8"
    bom = tmp_path / "bom.yaml"
    bom.write_bytes(b"\xef\xbb\xbf" + MINIMAL.encode())
    assert RobotEnvironment.from_yaml(bom).vla.id == "hello"


def test_invalid_utf8_names_the_offset(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes(MINIMAL.encode() + b"task: {instruction: caf\xe9}\n")
    error = _error(lambda: RobotEnvironment.from_yaml(path))
    assert "not UTF-8" in str(error)
    assert "0xe9" in str(error)


def test_nul_byte_in_path_is_a_config_error() -> None:
    error = _error(lambda: read_config_file("deploy\x00.yaml", field="--config"))
    assert "NUL" in str(error)
    assert error.field == "--config"


def test_tilde_is_expanded(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "cal.json").write_text('{"a": 1}')
    assert expand_user_path("~/cal.json") == tmp_path / "cal.json"
    assert load_config_file("~/cal.json") == {"a": 1}
    assert resolve_user_path("x.yaml", tmp_path) == tmp_path / "x.yaml"
    assert resolve_user_path("~/x.yaml", Path("/elsewhere")) == tmp_path / "x.yaml"


def test_duplicate_key_is_an_error_naming_key_and_line() -> None:
    text = MINIMAL + "safety:\n  client: envelope\nsafety:\n  client: null\n"
    error = _error(lambda: parse_config_text(text, source="deploy.yaml"))
    assert "duplicate key 'safety'" in str(error)
    assert "line 7" in str(error)


def test_duplicate_nested_key_is_an_error() -> None:
    error = _error(lambda: parse_config_text("a:\n  b: 1\n  b: 2\n", source="f"))
    assert "duplicate key 'b'" in str(error)


def test_merge_keys_still_work_and_explicit_keys_win() -> None:
    text = "base: &base {x: 1, y: 2}\nother: {y: 3}\nitem:\n  <<: [*base, {z: 4, x: 9}]\n  y: 5\n"
    assert parse_config_text(text, source="f")["item"] == {"y": 5, "x": 1, "z": 4}


def test_merge_key_bomb_is_refused_quickly() -> None:
    lines = ["a0: &a0 {k: v}"]
    for level in range(1, 30):
        prev = f"*a{level - 1}"
        lines.append(f"a{level}: &a{level} {{<<: [{', '.join([prev] * 9)}]}}")
    bomb = "\n".join(lines) + "\n"
    assert len(bomb) < 2000
    data = _finishes_quickly(lambda: parse_config_text(bomb, source="f"))  # merged keys are kept once
    assert data == {f"a{level}": {"k": "v"} for level in range(30)}


def test_alias_bomb_is_refused_by_the_expanded_size() -> None:
    lines = ["l0: &l0 [x, x, x, x, x, x, x, x, x, x]"]
    for level in range(1, 12):
        lines.append(f"l{level}: &l{level} [{', '.join([f'*l{level - 1}'] * 10)}]")
    outcome = _finishes_quickly(lambda: parse_config_text("\n".join(lines), source="f"))
    assert isinstance(outcome, ROSConfigError)
    assert f"more than {MAX_VALUES} values" in str(outcome)


def test_deep_nesting_is_refused() -> None:
    text = "a: " + "[" * 500 + "]" * 500 + "\n"
    error = _error(lambda: parse_config_text(text, source="deep.yaml"))
    assert "nested more than" in str(error)
    deep_json = "[" * 5000 + "]" * 5000
    assert "nested" in str(_error(lambda: parse_config_text(deep_json, source="deep.json", json_text=True)))


def test_recursive_alias_is_refused() -> None:
    error = _error(lambda: parse_config_text("a: &a [*a]\n", source="f"))
    assert "nested more than" in str(error)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("when: 2024-01-01\n", "a date"),
        ("blob: !!binary aGVsbG8=\n", "binary"),
        ("s: !!set {a, b}\n", "a set"),
        ("1: one\n", "not text"),
        ("on: true\n", "quote it"),
        ("x: !!python/object:os.system {}\n", "not valid YAML"),
        ("x: !custom 3\n", "not valid YAML"),
    ],
)
def test_values_that_are_not_plain_data_are_named(text: str, expected: str) -> None:
    assert expected in str(_error(lambda: parse_config_text(text, source="f")))


def test_yaml_syntax_error_is_one_line_with_position() -> None:
    error = _error(lambda: parse_config_text("a: [1, 2\nb: 3\n", source="bad.yaml"))
    assert "bad.yaml is not valid YAML" in str(error)
    assert "line" in str(error)


def test_json_duplicate_keys_are_refused() -> None:
    assert "duplicate key 'a'" in str(_error(lambda: parse_config_text('{"a": 1, "a": 2}', source="f", json_text=True)))


def test_booleans_and_text_are_not_numbers(tmp_path: Path) -> None:
    path = tmp_path / "d.yaml"
    path.write_text(MINIMAL + "rate_hz: true\n")
    error = _error(lambda: RobotEnvironment.from_yaml(path))
    assert error.field == "rate_hz"
    assert "boolean" in str(error)
    path.write_text(MINIMAL + "rate_hz: '30'\n")
    assert _error(lambda: RobotEnvironment.from_yaml(path)).field == "rate_hz"
    path.write_text(MINIMAL + "rate_hz: 30\nfaults: {max_consecutive_failures: 2}\n")
    assert RobotEnvironment.from_yaml(path).rate_hz == 30.0


def test_an_extreme_thumbnail_rate_is_refused_naming_the_shorthand(tmp_path: Path) -> None:
    path = tmp_path / "d.yaml"
    path.write_text(MINIMAL + "thumbnail_hz: 1.0e+300\n")
    error = _error(lambda: RobotEnvironment.from_yaml(path))
    assert "thumbnail_hz" in str(error)
    assert "observers" in str(error), "the message says what the shorthand stands for"


@pytest.mark.parametrize(
    ("extra", "field"),
    [
        ("realtime: {cpu_affinity: [1000000000000000000000000000000]}\n", "realtime.cpu_affinity[0]"),
        ("realtime: {cpu_affinity: []}\n", "realtime.cpu_affinity"),
        ("sensors: [{sensor_id: c, width: 1000000000000}]\n", "sensors[0].width"),
        ("sensors: [{sensor_id: c, fps: .inf}]\n", "sensors[0].fps"),
        ("sensors: [{sensor_id: c, fps: 5000}]\n", "sensors[0].fps"),
        ("rate_hz: .nan\n", "rate_hz"),
    ],
)
def test_extreme_numbers_are_refused_with_the_field(tmp_path: Path, extra: str, field: str) -> None:
    path = tmp_path / "d.yaml"
    path.write_text(MINIMAL + extra)
    assert _error(lambda: RobotEnvironment.from_yaml(path)).field == field


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("m" * 300 + ".onnx", "cannot be a file: File name too long"),
        ("exists.txt/inside.onnx", "cannot be a file: Not a directory"),
        ("missing.onnx", "model file not found"),
        (".", "is a directory, not a regular file"),
    ],
)
def test_a_path_that_cannot_be_a_file_is_a_config_error_naming_the_field(
    tmp_path: Path, name: str, expected: str
) -> None:
    (tmp_path / "exists.txt").write_text("x")
    assert not is_regular_file(tmp_path / name)
    with pytest.raises(ROSConfigError, match=expected) as caught:
        require_user_file(name, tmp_path, field="objects.model", what="model file")
    assert caught.value.field == "objects.model"


def test_require_user_file_resolves_against_the_deployment_folder(tmp_path: Path) -> None:
    (tmp_path / "model.onnx").write_bytes(b"x")
    assert require_user_file("model.onnx", tmp_path, field="f") == tmp_path / "model.onnx"
    assert is_regular_file(tmp_path / "model.onnx")
