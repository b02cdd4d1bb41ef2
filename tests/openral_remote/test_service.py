"""``PolicyService``, the transport-neutral core: one answer per job, an episode per client, freed when it leaves."""

from __future__ import annotations

import threading

import pytest

from openral_core import JointState, WorldState
from openral_remote.admission import ServeLimits
from openral_remote.service import Answer, PolicyService
from openral_remote.testing import ChunkSkill, chunk_meta, wait_for
from openral_rskill.chunks import ChunkRequest

pytestmark = pytest.mark.timeout(60)

NAMES = ["a0", "a1"]


class _Replies:
    """Every answer and error a job got, per job (a job must get exactly one)."""

    def __init__(self) -> None:
        self.got: dict[str, list[object]] = {}
        self.lock = threading.Lock()

    def callbacks(self, job: str) -> dict[str, object]:
        self.got[job] = []

        def answer(value: Answer) -> None:
            with self.lock:
                self.got[job].append(value)

        def error(text: str) -> None:
            with self.lock:
                self.got[job].append(text)

        return {"answer": answer, "error": error}


def _request(q: float) -> ChunkRequest:
    return ChunkRequest(WorldState(stamp_ns=1, joint_state=JointState(names=NAMES, positions=[q, 0.0])))


def _service(**kwargs: object) -> tuple[PolicyService, ChunkSkill]:
    skill = ChunkSkill(NAMES, **kwargs)  # type: ignore[arg-type]
    return PolicyService(skill, meta=chunk_meta(skill, rate_hz=30.0, model_hash="m"), limits=ServeLimits()), skill


def test_a_client_that_leaves_with_a_job_queued_is_freed_once_it_is_answered() -> None:
    service, skill = _service(delay_s=0.3)
    replies = _Replies()
    with service:
        service.infer("busy", _request(0.0), **replies.callbacks("first"))  # type: ignore[arg-type]
        assert wait_for(lambda: bool(skill.batch_sizes))  # the worker holds it
        service.infer("leaver", _request(0.1), **replies.callbacks("queued"))  # type: ignore[arg-type]
        service.leave("leaver")
        assert service.clients == 2  # its job is still to be answered
        assert wait_for(lambda: bool(replies.got["queued"]))
        assert wait_for(lambda: service.clients == 1)
        rows = replies.got["queued"][0]
        assert isinstance(rows, Answer)
        assert rows.rows[0, 0] == pytest.approx(0.6)
        service.leave("busy")
        assert wait_for(lambda: service.clients == 0)
    assert [len(got) for got in replies.got.values()] == [1, 1]


def test_close_answers_every_queued_job_once_and_a_decoder_error_is_a_bad_request() -> None:
    service, skill = _service(delay_s=0.3)
    replies = _Replies()
    service.start()
    service.infer("a", _request(0.0), **replies.callbacks("running"))  # type: ignore[arg-type]
    assert wait_for(lambda: bool(skill.batch_sizes))

    def broken() -> ChunkRequest:
        from openral_remote.codec import WireFormatError  # noqa: PLC0415

        raise WireFormatError("no such field")

    service.infer("b", broken, **replies.callbacks("broken"))  # type: ignore[arg-type]
    service.infer("c", _request(0.0), **replies.callbacks("waiting"))  # type: ignore[arg-type]
    service.close()
    assert all(len(got) == 1 for got in replies.got.values()), replies.got
    assert isinstance(replies.got["running"][0], Answer)
    assert replies.got["broken"] in (["shutting down"], ["WireFormatError: bad request: no such field"])
    assert replies.got["waiting"] == ["shutting down"]
