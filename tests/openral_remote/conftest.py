import fcntl
import hashlib
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

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


PEERS: dict[str, tuple[str, ...]] = {
    "openpi-client": ("openpi-client==0.1.2", "typing_extensions"),
    "openpi-server": ("openpi-server==0.1.0", "typing_extensions"),
    "vla-eval": ("vla-eval==0.8.0",),
}
"""Peer packages, pinned, installed unmodified in their own venvs (openpi's pin numpy<2; openpi-client
imports ``typing_extensions`` without declaring it)."""


class Peer:
    """A venv holding a peer package, and a way to run Python in it."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.python = root / "bin" / "python"

    def run(
        self, script: str, *args: str, timeout: float = 120.0, **kwargs: object
    ) -> "subprocess.CompletedProcess[Any]":
        """``python -c script args...`` in the venv, output captured (as text unless ``text=False``).

        Fails the test on a non-zero exit, quoting the peer's stderr.
        """
        kwargs.setdefault("text", True)
        done = subprocess.run(  # noqa: PLW1510
            [str(self.python), "-c", script, *args],
            capture_output=True,
            timeout=timeout,
            **kwargs,  # type: ignore[call-overload]
        )
        err = done.stderr if isinstance(done.stderr, str) else done.stderr.decode("utf-8", "replace")
        assert done.returncode == 0, f"peer script failed ({done.returncode}):\n{err[-4000:]}"
        return done  # type: ignore[no-any-return]

    def popen(self, script: str, *args: str, **kwargs: object) -> "subprocess.Popen[str]":
        """``python -c script args...`` in the venv, in the background."""
        return subprocess.Popen([str(self.python), "-c", script, *args], text=True, **kwargs)  # type: ignore[call-overload]


def _build_peer(root: Path, requirements: tuple[str, ...]) -> None:
    uv = shutil.which("uv")
    if uv is None:
        pytest.skip("peer venvs need uv on PATH")
    for command in (
        [uv, "venv", "--quiet", "--python", sys.executable, str(root)],
        [uv, "pip", "install", "--quiet", "--python", str(root / "bin" / "python"), *requirements],
    ):
        done = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)
        if done.returncode != 0:
            shutil.rmtree(root, ignore_errors=True)
            tail = " ".join(done.stderr.strip().splitlines()[-2:])
            pytest.skip(f"cannot make the peer venv ({' '.join(requirements)}), no network? {tail}")


@pytest.fixture(scope="session")
def peer_venv(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Callable[..., Peer]:
    """``peer_venv(name, *extra)``: a venv with the pinned peer ``name`` (a key of PEERS) and ``extra`` packages.

    Made once and cached under pytest's cache dir; a file lock keeps parallel test processes from
    building the same one twice. A venv that cannot be made (no network) skips the test.
    """
    cache = getattr(request.config, "cache", None)  # absent under -p no:cacheprovider: this session's temp dir
    base = Path(cache.mkdir("openral-peers")) if cache is not None else tmp_path_factory.mktemp("openral-peers")

    def get(name: str, *extra: str) -> Peer:
        requirements = (*PEERS[name], *extra)
        key = hashlib.sha256("\n".join([sys.executable, *requirements]).encode()).hexdigest()[:12]
        root = base / f"{name}-{key}"
        with (base / f"{name}-{key}.lock").open("w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (root / ".complete").exists():
                shutil.rmtree(root, ignore_errors=True)
                _build_peer(root, requirements)
                (root / ".complete").write_text("\n".join(requirements) + "\n")
        return Peer(root)

    return get
