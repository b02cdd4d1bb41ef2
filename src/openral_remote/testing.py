"""A policy server for tests, speaking the real protocol: run it as a child process and kill it as you like.

``python -m openral_remote.testing --listen tcp/127.0.0.1:PORT [--delay-ms D] [--offset X]`` serves
:class:`ChunkSkill` on the real Zenoh keys until SIGINT/SIGTERM (or SIGKILL, which is the point).
"""

from __future__ import annotations

import argparse
import signal
import socket
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from openral_core import RSkillInfo, WorldState
from openral_remote.allocator import keep_message_memory
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.meta import PolicyMeta
from openral_rskill.anchoring import AnchorSpec
from openral_rskill.base import ChunkingSkillBase
from openral_rskill.chunks import ChunkRequest

ROBOT = "test_robot"
POLICY = "chunks"


def wait_for(condition: Callable[[], bool], timeout_s: float = 20.0) -> bool:
    """Poll ``condition`` until it holds or ``timeout_s`` passes (a link's state changes on Zenoh's threads)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.005)
    return condition()


def free_endpoint() -> str:
    """A loopback TCP endpoint on a port free right now (for a test's or a benchmark's server)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


class ChunkSkill(ChunkingSkillBase):
    """Row ``j`` of a chunk is ``base + offset + j * step``: ``base`` the observed joints (zeros without).

    Args:
        action_names: The action's dimensions.
        chunk_size: Rows per chunk.
        offset: Added to every row (two "models" differ by it).
        step: Added per row.
        delay_s: Time each inference takes (a GPU's, or a hang when long); a batch takes it once.
        observation: What it says it reads (the client sends only that; empty: everything).
        latch: Keep episode state: ``base`` is the joints of the episode's first inference (an
            expert that plans from where it started), so the skill cannot be shared between episodes.
        batch: Requests one inference takes (``batch_sizes`` records each inference's).
    """

    def __init__(
        self,
        action_names: Sequence[str],
        *,
        chunk_size: int = 10,
        offset: float = 0.5,
        step: float = 0.01,
        delay_s: float = 0.0,
        observation: Sequence[str] = ("joint_state",),
        latch: bool = False,
        batch: int = 1,
    ) -> None:
        super().__init__()
        self._action_names = list(action_names)
        self.chunk_size = chunk_size
        self.offset = offset
        self.step_size = step
        self.delay_s = delay_s
        self.latch = latch
        self.batch = batch
        self.seeds: list[int | None] = []
        self.batch_sizes: list[int] = []
        self._latched: np.ndarray | None = None
        self._info = RSkillInfo(skill_id="chunk_test", chunk_size=chunk_size, observation=list(observation))

    @property
    def info(self) -> RSkillInfo:
        return self._info

    @property
    def action_names(self) -> list[str]:
        return self._action_names

    def rows(self, world: WorldState) -> np.ndarray:
        """The chunk for ``world`` (what a client must receive)."""
        base = np.zeros(len(self.action_names))
        joints = world.joint_state
        if joints is not None and len(joints.positions) == len(base):
            base = np.asarray(joints.positions, dtype=np.float64)
        if self.latch:
            if self._latched is None:
                self._latched = base
            base = self._latched
        steps = self.step_size * np.arange(self.chunk_size)[:, None]
        return np.asarray(base + self.offset + steps)

    def serves_many_episodes(self) -> bool:
        return not self.latch

    def batch_capacity(self) -> int:
        return self.batch

    def _on_reset(self) -> None:
        self.seeds.append(self.episode_seed)
        self._latched = None

    def _chunk_impl(self, request: ChunkRequest) -> np.ndarray:
        return self._chunks_impl([request])[0]

    def _chunks_impl(self, requests: Sequence[ChunkRequest]) -> list[np.ndarray]:
        self.batch_sizes.append(len(requests))
        if self.delay_s:
            time.sleep(self.delay_s)
        return [self.rows(request.world) for request in requests]


def chunk_meta(skill: ChunkSkill, *, rate_hz: float, model_hash: str) -> PolicyMeta:
    """The meta a server of ``skill`` publishes."""
    return PolicyMeta(
        policy=POLICY,
        robot=ROBOT,
        skill_id=skill.info.skill_id,
        chunk_size=skill.chunk_size,
        action_names=skill.action_names,
        control_mode=skill.info.control_mode,
        anchor=AnchorSpec(),
        dt_s=1.0 / rate_hz,
        observation=list(skill.info.observation),
        model_hash=model_hash,
    )


def serve(args: Any) -> None:
    """Serve a :class:`ChunkSkill` until SIGINT or SIGTERM, under a Zenoh id claimed as 'openral serve' claims it."""
    from openral_remote.config import TlsConfig  # noqa: PLC0415
    from openral_remote.identity import claim_server_id  # noqa: PLC0415
    from openral_remote.server import PolicyServer  # noqa: PLC0415 (Zenoh: loaded where it is used)

    names = [f"a{i}" for i in range(args.dims)]
    skill = ChunkSkill(
        names,
        chunk_size=args.chunk_size,
        offset=args.offset,
        delay_s=args.delay_ms / 1e3,
        observation=[] if args.observation == ["all"] else args.observation,
    )
    meta = chunk_meta(skill, rate_hz=args.rate_hz, model_hash=args.model_hash)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    keep_message_memory()  # as 'openral serve' does
    keys = PolicyKeys.of(ROBOT, POLICY)
    tls = None
    if args.tls_ca is not None:
        tls = TlsConfig(ca=args.tls_ca, cert=args.tls_cert, key=args.tls_key, mutual=args.mtls)
    with claim_server_id(keys, args.zenoh_id) as identity:
        zenoh = ZenohConfig(listen=[args.listen], lease_ms=args.lease_ms, id=identity.zid, tls=tls, allow=args.allow)
        with PolicyServer(skill, keys=keys, zenoh=zenoh, meta=meta):
            stop.wait()


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--listen", required=True)
    parser.add_argument("--dims", type=int, default=2)
    parser.add_argument("--chunk-size", type=int, default=10)
    parser.add_argument("--offset", type=float, default=0.5)
    parser.add_argument("--delay-ms", type=float, default=0.0)
    parser.add_argument("--rate-hz", type=float, default=10.0)
    parser.add_argument("--model-hash", default="model-a")
    parser.add_argument("--lease-ms", type=int, default=1000)
    parser.add_argument("--observation", nargs="+", default=["joint_state"], help="Fields read; 'all' for all.")
    parser.add_argument("--zenoh-id", default=None, help="Zenoh id (default: the one kept for the key on this host).")
    parser.add_argument("--tls-ca", default=None, help="TLS: the CA certificate (with --tls-cert, --tls-key).")
    parser.add_argument("--tls-cert", default=None)
    parser.add_argument("--tls-key", default=None)
    parser.add_argument("--mtls", action="store_true", help="Mutual TLS: clients need a certificate too.")
    parser.add_argument("--allow", nargs="+", default=[], help="Certificate common names allowed (access control).")
    serve(parser.parse_args(argv))


if __name__ == "__main__":
    main()
