import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator

import pytest

from openral_remote.client import RemotePolicyClient
from openral_remote.config import ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.testing import POLICY, ROBOT, free_endpoint


class ServerProcess:
    """A policy server (``python -m openral_remote.testing``) in a child process."""

    def __init__(self, endpoint: str, args: list[str]) -> None:
        self.endpoint = endpoint
        self.args = args
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> "ServerProcess":
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "openral_remote.testing", "--listen", self.endpoint, *self.args],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        return self

    def kill(self) -> None:
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGKILL)
        self.stderr = self._reap()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
        self.stderr = self._reap()

    def _reap(self) -> str:
        """Wait for the process to end and return what it wrote on stderr (the pipe is closed)."""
        if self.proc is None or self.proc.stderr is None:
            return ""
        try:
            _out, err = self.proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _out, err = self.proc.communicate(timeout=10)
        return err.decode("utf-8", "replace")


@pytest.fixture
def endpoint() -> str:
    return free_endpoint()


@pytest.fixture
def server(endpoint: str) -> Iterator[Callable[..., ServerProcess]]:
    started: list[ServerProcess] = []

    def start(*args: str) -> ServerProcess:
        process = ServerProcess(endpoint, list(args)).start()
        started.append(process)
        return process

    yield start
    for process in started:
        process.stop()


@pytest.fixture
def keys() -> PolicyKeys:
    return PolicyKeys.of(ROBOT, POLICY)


@pytest.fixture
def client_zenoh(endpoint: str) -> ZenohConfig:
    return ZenohConfig(connect=[endpoint])


@pytest.fixture
def client(keys: PolicyKeys, client_zenoh: ZenohConfig) -> Iterator[Callable[..., RemotePolicyClient]]:
    """Connected clients of the test server (closed after the test); keyword arguments go to the client."""
    made: list[RemotePolicyClient] = []

    def connect(deadline_ms: float = 1000.0, **kwargs: object) -> RemotePolicyClient:
        remote = RemotePolicyClient(keys, client_zenoh, deadline_ms=deadline_ms, **kwargs)  # type: ignore[arg-type]
        made.append(remote)
        remote.connect(timeout_s=20.0)
        return remote

    yield connect
    for remote in made:
        remote.close()
