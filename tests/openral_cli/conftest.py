"""Checks that ``deploy`` and ``sim run`` share: what their ``--mcap`` and ``--foxglove`` flags must produce."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest


def _check_bag(
    recording: Path, *, ticks: int | None = None, worlds: int | None = None, attached: list[str] | None = None
) -> None:
    """A ROS 2 bag with one message per tick, one joint-state message per tick with a world state, the file attached.

    ``worlds`` defaults to ``ticks`` (a robot reads its state every tick; a simulator's reset tick has none).
    """
    from mcap.reader import make_reader  # noqa: PLC0415 (the 'dataset' extra)

    with recording.open("rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        topics = [channel.topic for _schema, channel, _message in reader.iter_messages()]
    if ticks is not None:
        assert topics.count("/openral/tick") == ticks
        assert topics.count("/joint_states") == (ticks if worlds is None else worlds)
    if attached is not None:
        with recording.open("rb") as stream:
            assert [a.name for a in make_reader(stream).iter_attachments()] == attached


def _check_foxglove_served(output: str) -> None:
    assert "foxglove: ws://127.0.0.1:" in output, "the flag's observer was built, started and printed"


@pytest.fixture
def check_bag() -> Callable[..., None]:
    """``check_bag(recording, ticks=N, attached=[name])``: what ``--mcap`` writes."""
    pytest.importorskip("rosbags", reason="needs the 'dataset' extra")
    return _check_bag


@pytest.fixture
def check_foxglove_served() -> Callable[[str], None]:
    """``check_foxglove_served(output)``: ``--foxglove`` started a live server and said where."""
    pytest.importorskip("foxglove", reason="needs the 'foxglove' extra")
    return _check_foxglove_served
