"""``TeeManager``: attach and detach consumer branches on a running pipeline's camera tee.

A branch is ``<leaky queue> ! <elements>`` in a bin of its own, linked to a new request pad of
the tee named :data:`~openral_runner.backends.gstreamer.pipeline.TEE_NAME` and brought to the
pipeline's state; the leaky queue keeps a slow consumer from ever holding the policy's leg back.
A failed link or state change rolls everything back (pad released, bin removed). Detaching
waits for the tee's pad to be idle (a pad probe), unlinks there, then stops and removes the bin
and releases the pad: never mid-buffer, idempotent, bounded by a timeout.
"""

from __future__ import annotations

import itertools
import threading
from dataclasses import dataclass, field
from typing import Any, Final

import structlog

from openral_core import ROSConfigError, ROSRuntimeError
from openral_runner.backends.gstreamer.gst import Gst
from openral_runner.backends.gstreamer.pipeline import LEAKY_BRANCH_QUEUE, TEE_NAME

_log = structlog.get_logger(__name__)

DETACH_TIMEOUT_S: Final = 2.0
"""Longest a detach waits for the tee's pad to go idle before removing the branch regardless."""


@dataclass
class BranchHandle:
    """An attached branch: give it back to :meth:`TeeManager.detach`."""

    name: str
    pad: Any
    bin: Any
    detached: bool = field(default=False)


class TeeManager:
    """Branches on one tee of one pipeline.

    Raises:
        ROSConfigError: The pipeline has no element named ``tee_name``.
    """

    def __init__(self, pipeline: Any, *, tee_name: str = TEE_NAME) -> None:
        tee = pipeline.get_by_name(tee_name)
        if tee is None:
            raise ROSConfigError(
                f"the pipeline has no tee named {tee_name!r}",
                field="tee_name",
                hint="build it with enable_event_tee or enable_ros_tee, or name a tee in the pipeline string",
            )
        self.pipeline = pipeline
        self.tee = tee
        self._branches: dict[str, BranchHandle] = {}
        self._lock = threading.Lock()
        self._ids = itertools.count()

    @property
    def branch_count(self) -> int:
        """Branches attached now."""
        return len(self._branches)

    def attach(self, elements: str, *, name: str | None = None) -> BranchHandle:
        """Parse ``elements`` behind the leaky queue into a bin, link it to the tee and start it with the pipeline.

        Raises:
            ROSConfigError: ``elements`` does not parse, or ``name`` is attached already.
            ROSRuntimeError: Linking or starting failed (everything is rolled back).
        """
        branch_name = name or f"openral_branch_{next(self._ids)}"
        with self._lock:
            if branch_name in self._branches:
                raise ROSConfigError(f"a branch named {branch_name!r} is attached already", field="name")
            try:
                branch = Gst.parse_bin_from_description(f"{LEAKY_BRANCH_QUEUE} ! {elements}", True)
            except Exception as exc:  # GLib.Error: the description does not parse
                raise ROSConfigError(f"cannot build the branch {elements!r}: {exc}", field="elements") from exc
            branch.set_name(branch_name)
            self.pipeline.add(branch)
            pad = self.tee.request_pad_simple("src_%u")
            handle = BranchHandle(branch_name, pad, branch)
            if pad is None:
                self._roll_back(handle)
                raise ROSRuntimeError(f"the tee gave no pad for branch {branch_name!r}")
            result = pad.link(branch.get_static_pad("sink"))
            if result != Gst.PadLinkReturn.OK:
                self._roll_back(handle)
                raise ROSRuntimeError(f"cannot link branch {branch_name!r} to the tee: {result.value_nick}")
            if not branch.sync_state_with_parent():
                pad.unlink(branch.get_static_pad("sink"))
                self._roll_back(handle)
                raise ROSRuntimeError(f"branch {branch_name!r} did not start with the pipeline")
            self._branches[branch_name] = handle
        return handle

    def detach(self, handle: BranchHandle, *, timeout_s: float = DETACH_TIMEOUT_S) -> None:
        """Unlink the branch when its tee pad is idle, stop and remove it, release the pad. Idempotent."""
        with self._lock:
            if handle.detached:
                return
            handle.detached = True
            self._branches.pop(handle.name, None)
        sink_pad = handle.bin.get_static_pad("sink")
        unlinked = threading.Event()

        def on_idle(pad: Any, _info: Any) -> Any:
            pad.unlink(sink_pad)
            unlinked.set()
            return Gst.PadProbeReturn.REMOVE

        handle.pad.add_probe(Gst.PadProbeType.IDLE, on_idle)
        if not unlinked.wait(timeout_s):
            _log.warning("tee pad never went idle; removing the branch anyway", branch=handle.name)
            handle.pad.unlink(sink_pad)
        self._roll_back(handle)

    def detach_all(self) -> None:
        """Detach every branch (on the way out)."""
        for handle in list(self._branches.values()):
            self.detach(handle)

    def _roll_back(self, handle: BranchHandle) -> None:
        handle.bin.set_state(Gst.State.NULL)
        self.pipeline.remove(handle.bin)
        if handle.pad is not None:
            self.tee.release_request_pad(handle.pad)
