"""TeeManager on real playing pipelines: branches come and go, the policy's leg never stalls, nothing leaks."""

from __future__ import annotations

import importlib
import threading
import time

import pytest

from openral_core import ROSConfigError

pytestmark = pytest.mark.gstreamer

pytest.importorskip(
    "gi", reason="needs GStreamer and PyGObject: run scripts/install-system-deps.sh, then uv sync --extra gstreamer"
)
try:
    tee_module = importlib.import_module("openral_runner.backends.gstreamer.tee_manager")
except ROSConfigError as exc:  # gi present, GStreamer typelibs missing
    pytest.skip(f"GStreamer introspection data missing: {exc}", allow_module_level=True)

from gi.repository import Gst  # noqa: E402

from openral_runner.backends.gstreamer.pipeline import TEE_NAME, leaky_branch  # noqa: E402

TeeManager = tee_module.TeeManager


class Counter:
    def __init__(self) -> None:
        self.count = 0
        self.changed = threading.Condition()

    def on_sample(self, sink) -> Gst.FlowReturn:
        sink.emit("pull-sample")
        with self.changed:
            self.count += 1
            self.changed.notify_all()
        return Gst.FlowReturn.OK

    def wait_beyond(self, count: int, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        with self.changed:
            while self.count <= count:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self.changed.wait(left)
        return True


@pytest.fixture
def playing():
    description = (
        "videotestsrc is-live=true pattern=ball ! video/x-raw,format=BGR,width=64,height=48,framerate=60/1 "
        f"! tee name={TEE_NAME} allow-not-linked=true "
        + leaky_branch("appsink name=policy_sink emit-signals=true sync=false max-buffers=1 drop=true")
    )
    pipeline = Gst.parse_launch(description)
    policy = Counter()
    pipeline.get_by_name("policy_sink").connect("new-sample", policy.on_sample)
    assert pipeline.set_state(Gst.State.PLAYING) != Gst.StateChangeReturn.FAILURE
    assert policy.wait_beyond(0), "the pipeline never delivered a frame"
    yield pipeline, policy
    pipeline.set_state(Gst.State.NULL)


def test_fifty_attach_detach_cycles_leak_nothing_and_never_stall_the_policy(playing):
    pipeline, policy = playing
    manager = TeeManager(pipeline)
    tee = pipeline.get_by_name(TEE_NAME)
    pads_before = len(tee.srcpads)
    children_before = pipeline.get_children_count()
    for cycle in range(50):
        branch = Counter()
        handle = manager.attach(
            f"videoconvert ! appsink name=branch_sink_{cycle} emit-signals=true sync=false max-buffers=1 drop=true",
            name=f"branch_{cycle}",
        )
        handle.bin.get_by_name(f"branch_sink_{cycle}").connect("new-sample", branch.on_sample)
        assert branch.wait_beyond(0), f"cycle {cycle}: the branch got no frame"
        assert manager.branch_count == 1
        seen = policy.count
        manager.detach(handle)
        manager.detach(handle)  # idempotent
        assert policy.wait_beyond(seen), f"cycle {cycle}: the policy's leg stalled"
    assert manager.branch_count == 0
    assert len(tee.srcpads) == pads_before
    assert pipeline.get_children_count() == children_before
    _state, current, _pending = pipeline.get_state(0)
    assert current == Gst.State.PLAYING


def test_a_branch_that_cannot_link_is_rolled_back(playing):
    pipeline, policy = playing
    manager = TeeManager(pipeline)
    tee = pipeline.get_by_name(TEE_NAME)
    pads_before, children_before = len(tee.srcpads), pipeline.get_children_count()
    with pytest.raises(ROSConfigError, match="cannot build"):
        manager.attach("no_such_element_anywhere ! fakesink")
    # Caps the tee's BGR stream cannot meet: the link fails and nothing is left behind.
    with pytest.raises(Exception, match=r"link|start"):
        manager.attach("capsfilter caps=audio/x-raw ! fakesink")
    assert len(tee.srcpads) == pads_before
    assert pipeline.get_children_count() == children_before
    assert policy.wait_beyond(policy.count)  # the policy's leg runs on
    with pytest.raises(ROSConfigError, match="no tee"):
        TeeManager(pipeline, tee_name="missing_tee")
