"""RecordingHAL: records calls, fails on cue, and keeps the HAL contract."""

from __future__ import annotations

import pytest

from openral_core import Action, ROSConfigError, ROSHardwareError
from openral_hal import HAL, connected
from openral_hal.testing import RecordingHAL


def test_is_a_hal_and_records_calls_in_order() -> None:
    hal = RecordingHAL(["a", "b"])
    assert isinstance(hal, HAL)

    with connected(hal):
        hal.read_state()
        hal.send_action(Action(joint_names=["b"], targets=[[0.5]]))
        hal.estop()

    assert hal.calls == ["connect", "read_state", "send_action", "estop", "disconnect"]
    assert (hal.connect_calls, hal.disconnect_calls, hal.estop_calls, hal.read_calls) == (1, 1, 1, 1)
    assert [a.first for a in hal.sent] == [[0.5]]
    assert not hal.is_connected


def test_state_echoes_the_last_command_with_the_injected_clock() -> None:
    hal = RecordingHAL(["a", "b"], initial_positions=[1.0, 2.0], clock_ns=lambda: 42)
    hal.connect()
    hal.send_action(Action(joint_names=["b"], targets=[[0.5]]))
    state = hal.read_state()
    assert state.positions == [1.0, 0.5]
    assert state.stamp_ns == 42


def test_scripted_faults() -> None:
    hal = RecordingHAL(["a"], fail_read_on={1}, fail_send_on={0})
    hal.connect()
    hal.read_state()
    with pytest.raises(ROSHardwareError, match="call 1"):
        hal.read_state()
    hal.read_state()
    with pytest.raises(ROSHardwareError, match="call 0"):
        hal.send_action(Action(joint_names=["a"], targets=[[0.1]]))
    hal.send_action(Action(joint_names=["a"], targets=[[0.2]]))
    assert [a.first for a in hal.attempted] == [[0.1], [0.2]]
    assert [a.first for a in hal.sent] == [[0.2]]


def test_fail_connect_until_healed() -> None:
    hal = RecordingHAL(["a"], fail_connect=ROSHardwareError("no bus"))
    with pytest.raises(ROSHardwareError, match="no bus"):
        hal.connect()
    assert not hal.is_connected
    hal.fail_connect = None
    hal.connect()
    assert hal.is_connected
    assert hal.connect_calls == 2


def test_on_send_hook_sees_each_applied_action() -> None:
    seen: list[Action] = []
    hal = RecordingHAL(["a"], on_send=seen.append)
    hal.connect()
    action = Action(joint_names=["a"], targets=[[0.1]])
    hal.send_action(action)
    assert seen == [action]


def test_contract_errors_match_real_adapters() -> None:
    hal = RecordingHAL(["a"])
    with pytest.raises(ROSHardwareError, match="not connected"):
        hal.read_state()
    hal.connect()
    with pytest.raises(ROSConfigError, match="no joint 'z'"):
        hal.send_action(Action(joint_names=["z"], targets=[[0.1]]))
    assert hal.sent == []


def test_for_robot_uses_the_shipped_manifest() -> None:
    hal = RecordingHAL.for_robot("so101_follower", fail_read_on={0})
    assert hal.robot_id == "so101_follower"
    assert hal.joint_names[0] == "shoulder_pan"
    assert hal.fail_read_on == {0}
