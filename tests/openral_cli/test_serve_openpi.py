"""``openral serve --protocol openpi``: its options checked before anything loads, the risk named, a profile served."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner
from websockets.sync.client import connect

from openral_cli import main
from openral_remote.msgpack_numpy import packb, unpackb
from openral_remote.testing import wait_for

pytestmark = pytest.mark.timeout(180)


def _recv(ws: Any) -> Any:
    """The next frame, decoded (a text frame fails the test, quoting it)."""
    reply = ws.recv(timeout=20)
    assert isinstance(reply, bytes), reply
    return unpackb(reply)


def _serve(*args: str) -> tuple[int, str]:
    # An unknown skill would be the error if anything after the options' checks ran.
    out = CliRunner().invoke(main.cli, ["serve", "--skill", "no_such_skill", *args])
    return out.exit_code, out.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--protocol", "openpi", "--listen", "nonsense"], "--listen: --listen 'nonsense' is not HOST:PORT"),
        (["--protocol", "openpi", "--listen", "h:70000"], "is not HOST:PORT"),
        (["--protocol", "openpi", "--listen", "a:1", "--listen", "b:2"], "listens on one HOST:PORT"),
        (["--protocol", "openpi", "--connect", "tcp/1.2.3.4:7447"], "--connect is for --protocol zenoh"),
        (["--protocol", "openpi", "--zenoh-id", "abc"], "--zenoh-id is for --protocol zenoh"),
        (["--protocol", "vla-eval", "--openpi-profile", "libero"], "--openpi-profile is for --protocol openpi"),
        (["--openpi-profile", "libero"], "--openpi-profile is for the websocket protocols"),
        (["--protocol", "openpi", "--api-key-file", "/no/such/key"], "--api-key-file"),
    ],
)
def test_an_option_that_does_not_fit_the_protocol_is_one_line_and_exit_2(args: list[str], message: str) -> None:
    code, err = _serve(*args)
    assert code == 2, err
    assert message in err
    assert len(err.strip().splitlines()) == 1


def test_an_api_key_file_must_hold_a_key_and_is_not_for_zenoh(tmp_path: Path) -> None:
    empty = tmp_path / "empty.key"
    empty.write_text("\n  \n")
    code, err = _serve("--protocol", "openpi", "--api-key-file", str(empty))
    assert code == 2
    assert "holds no API key" in err
    key = tmp_path / "api.key"
    key.write_text("k3y\n")
    code, err = _serve("--api-key-file", str(key))
    assert code == 2
    assert "--api-key-file is for the websocket protocols" in err


def test_a_bind_beyond_loopback_without_a_key_or_tls_names_the_risk(tmp_path: Path) -> None:
    code, err = _serve("--protocol", "openpi", "--listen", "0.0.0.0:0")
    assert code == 2  # the unknown skill, after the warning
    assert "warning: serving on 0.0.0.0:0 without --api-key-file or --tls-*" in err
    key = tmp_path / "api.key"
    key.write_text("k3y\n")
    for listen, extra in (("0.0.0.0:0", ["--api-key-file", str(key)]), ("127.0.0.1:0", []), ("localhost:0", [])):
        code, err = _serve("--protocol", "openpi", "--listen", listen, *extra)
        assert code == 2
        assert "warning" not in err


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _healthy(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=2) as response:
            return bool(response.status == 200)
    except (urllib.error.URLError, ConnectionError, TimeoutError):
        return False


def test_the_libero_profile_takes_openpis_libero_observation() -> None:
    port = _free_port()
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "openral_cli",
            "serve",
            "--protocol",
            "openpi",
            "--openpi-profile",
            "libero",
            "--skill",
            "hello",
            "--skill-params",
            '{"chunk_size": 5}',
            "--listen",
            f"127.0.0.1:{port}",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert wait_for(lambda: server.poll() is not None or _healthy(port), timeout_s=120)
        assert server.poll() is None, server.communicate()[1]
        image = np.zeros((224, 224, 3), np.uint8)
        obs = {
            "observation/image": image,
            "observation/wrist_image": image,
            "observation/state": np.zeros(8, np.float32),
            "prompt": "put the bowl on the plate",
        }
        url = f"ws://127.0.0.1:{port}"
        with connect(url, compression=None, max_size=None, open_timeout=20) as ws:
            assert _recv(ws)["action_horizon"] == 5
            ws.send(packb(obs))
            # Taken and turned into a world state of LIBERO's 8-d state: SO-101's hello skill then names the mismatch.
            assert "it reports ['eef_x', 'eef_y', 'eef_z', 'eef_rx'" in str(ws.recv(timeout=20))
        with connect(url, compression=None, max_size=None, open_timeout=20) as ws:
            ws.recv(timeout=20)
            ws.send(packb({**obs, "observation/state": np.zeros(7, np.float32)}))
            assert "shape (7,) where (8,) is expected" in str(ws.recv(timeout=20))  # refused before decoding
    finally:
        server.send_signal(signal.SIGINT)
        _out, err = server.communicate(timeout=60)
    assert server.returncode == 0, err
    assert "refused 1, errors 1" in err
