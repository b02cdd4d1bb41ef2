"""The ROS 2 bag: CDR messages under ROS 2 message definitions, read back with an independent ROS 2 decoder."""

from __future__ import annotations

import contextlib
import io
import json
from collections import Counter
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image

from openral_core import ObserverContext, ROSConfigError, SensorReaderConfig, TickResult
from openral_dataset.ros2_bag import NOT_IN_TICK_RECORD, Ros2BagWriter
from openral_hal.testing import RecordingHAL
from openral_rskill.testing import ScriptedSkill
from openral_runner.hardware import HardwareRunner
from openral_runner.testing import FakeClock, ScriptedReader
from openral_world_state import WorldStateAggregator

JOINTS = ["j0", "j1", "j2"]


def _run(tmp_path: Path) -> tuple[Path, HardwareRunner, Ros2BagWriter]:
    deployment = tmp_path / "robot.yaml"
    deployment.write_text("name: bag-test\n")
    path = tmp_path / "session.mcap"
    bag = Ros2BagWriter(path, joint_names=JOINTS, deployment=deployment)
    clock = FakeClock()
    skill = ScriptedSkill(JOINTS, actions=[[0.1 * i, 0.2, 0.3] for i in range(1, 50)])
    skill.configure()
    skill.activate()
    runner = HardwareRunner(
        hal=RecordingHAL(JOINTS, clock_ns=clock.now_ns),
        skill=skill,
        aggregator=WorldStateAggregator(sensors=[SensorReaderConfig(sensor_id="front")], clock=clock.now_ns),
        sensor_readers=[ScriptedReader("front", clock, width=32, height=24)],
        rate_hz=30.0,
        clock=clock,
        thumbnail_hz=1000.0,
    )
    runner.observers.append(bag)
    runner.activate()
    runner.episode_start("pick")
    runner.run(12)
    runner.episode_end(success=True)
    runner.deactivate()
    return path, runner, bag


class _Decoded:
    def __init__(self, schema, channel, ros_msg) -> None:
        self.schema, self.channel, self.ros_msg = schema, channel, ros_msg


def read_ros2_messages(path: str) -> list[_Decoded]:
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        return [_Decoded(s, c, m) for s, c, _raw, m in reader.iter_decoded_messages()]


def _records(stream: io.BytesIO) -> list[object]:
    """Every record a streaming reader gets out of ``stream`` before it stops (at a torn record)."""
    records: list[object] = []
    with contextlib.suppress(Exception):
        records.extend(StreamReader(stream, skip_magic=False).records)
    return records


def test_every_tick_is_in_the_bag_as_ros2_messages(tmp_path: Path) -> None:
    path, runner, bag = _run(tmp_path)
    assert bag.errors == 0
    messages = list(read_ros2_messages(str(path)))
    topics = Counter(m.channel.topic for m in messages)
    assert topics["/joint_states"] == topics["/openral/command/sent"] == topics["/openral/tick"] == 12
    assert topics["/openral/episode"] == 2
    assert topics["/camera/front/compressed"] >= 1
    schemas = {m.channel.topic: m.schema.name for m in messages}
    assert schemas["/joint_states"] == "sensor_msgs/msg/JointState"
    assert schemas["/camera/front/compressed"] == "sensor_msgs/msg/CompressedImage"

    sent = [m.ros_msg for m in messages if m.channel.topic == "/openral/command/sent"]
    assert [list(s.position) for s in sent] == [t.sent_action for t in runner.recent_ticks]  # float64 both ways
    assert sent[0].name == JOINTS
    ticks = [json.loads(m.ros_msg.data) for m in messages if m.channel.topic == "/openral/tick"]
    assert [t["tick_idx"] for t in ticks] == [t.tick_idx for t in runner.recent_ticks]
    assert ticks[0]["episode_idx"] == 0
    episodes = [json.loads(m.ros_msg.data) for m in messages if m.channel.topic == "/openral/episode"]
    assert episodes == [
        {"event": "start", "episode_idx": 0, "task": "pick"},
        {"event": "end", "episode_idx": 0, "success": True, "kept": True},
    ]
    image = next(m.ros_msg for m in messages if m.channel.topic == "/camera/front/compressed")
    assert image.format == "jpeg"
    assert Image.open(io.BytesIO(bytes(image.data))).size == (32, 24)
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        (attachment,) = list(reader.iter_attachments())
    assert attachment.name == "robot.yaml"
    assert attachment.data == b"name: bag-test\n"


def test_a_bag_cut_short_stays_readable_up_to_its_last_whole_message(tmp_path: Path) -> None:
    path, _, _ = _run(tmp_path)
    data = path.read_bytes()
    cut = io.BytesIO(data[: len(data) * 2 // 3])  # a crash: no summary, no footer, a torn record
    records = _records(cut)
    assert sum(type(r).__name__ == "Message" for r in records) > 10


def test_an_existing_bag_is_not_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "taken.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(ROSConfigError, match="--mcap"):
        Ros2BagWriter(path, joint_names=JOINTS)
    assert path.read_bytes() == b"precious"


def test_building_creates_no_file_and_start_creates_it(tmp_path: Path) -> None:
    path = tmp_path / "later.mcap"
    bag = Ros2BagWriter(path, joint_names=JOINTS, field="observers[].params.path")
    assert not path.exists()  # what openral validate builds leaves nothing behind
    bag.close()
    assert not path.exists()
    bag = Ros2BagWriter(path, joint_names=JOINTS)
    bag.start()
    bag.start()
    bag.close()
    with open(path, "rb") as stream:
        assert make_reader(stream).get_header().profile == "ros2"


def test_a_missing_folder_is_refused_when_built_naming_the_field(tmp_path: Path) -> None:
    with pytest.raises(ROSConfigError, match=r"observers\[\]\.params\.path: .*no folder"):
        Ros2BagWriter(tmp_path / "nope" / "run.mcap", joint_names=JOINTS, field="observers[].params.path")


def test_the_tick_record_is_every_tick_result_field_with_a_value_but_those_placed_elsewhere(tmp_path: Path) -> None:
    path = tmp_path / "fields.mcap"
    simulated = TickResult(
        tick_idx=4,
        tick_ms=1.5,
        action_applied=False,
        withheld_reason="safety",
        requested_action=[0.1, 0.2, 0.3],
        lateness_ms=0.0,
        step_idx=3,
        episode_idx=0,
        reward=0.5,
        terminated=False,
        truncated=False,
    )
    bag = Ros2BagWriter(path, joint_names=JOINTS)
    bag.start()
    bag.on_tick(simulated, None)
    bag.close()
    assert set(TickResult.model_fields) >= NOT_IN_TICK_RECORD
    (record,) = [
        json.loads(m.ros_msg.data) for m in read_ros2_messages(str(path)) if m.channel.topic == "/openral/tick"
    ]
    with_value = {name for name, value in simulated if value is not None}
    assert set(record) == with_value - NOT_IN_TICK_RECORD
    assert (record["withheld_reason"], record["reward"], record["terminated"]) == ("safety", 0.5, False)


@pytest.mark.parametrize("attach", ["missing.yaml", "/dev/zero", "big.yaml", "folder"])
def test_an_attachment_that_is_not_a_small_regular_file_is_refused_before_the_bag_exists(
    tmp_path: Path, attach: str
) -> None:
    (tmp_path / "big.yaml").write_bytes(b"#" * ((1 << 20) + 1))
    (tmp_path / "folder").mkdir()
    path = tmp_path / "run.mcap"
    with pytest.raises(ROSConfigError) as refused:
        Ros2BagWriter.from_config(
            {"path": "run.mcap", "attach": attach},
            ObserverContext(robot_id="so101_follower", rate_hz=30.0, joint_names=tuple(JOINTS), base_dir=tmp_path),
        )
    assert refused.value.field == "observers[].params.attach"
    assert not path.exists()
