"""``openral serve`` and ``remote_policy`` with TLS: bad files are one line and exit 2 before anything connects."""

from __future__ import annotations

import datetime as dt
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from openral_cli import main
from openral_remote.client import RemotePolicyClient, ServerUnavailable
from openral_remote.config import TlsConfig, ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.testing import free_endpoint
from openral_remote.testing_tls import Issued, make_ca, make_certificate

pytestmark = pytest.mark.timeout(120)


@dataclass(frozen=True)
class Files:
    ca: Issued
    server: Issued
    robot: Issued
    intruder: Issued
    expired: Issued
    future: Issued
    not_pem: Path
    missing: Path


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Files:
    folder = tmp_path_factory.mktemp("tls")
    ca = make_ca(folder)
    now, a_day = dt.datetime.now(dt.UTC), dt.timedelta(days=1)
    not_pem = folder / "ca-notes.txt"
    not_pem.write_text("not a certificate\n")
    return Files(
        ca=ca,
        server=make_certificate(folder, "policy-server", ca),
        robot=make_certificate(folder, "robot-1", ca),
        intruder=make_certificate(folder, "intruder", ca),
        expired=make_certificate(folder, "expired", ca, valid_from=now - 2 * a_day, valid_until=now - a_day),
        future=make_certificate(folder, "future", ca, valid_from=now + a_day),
        not_pem=not_pem,
        missing=folder / "nowhere" / "ca.crt",
    )


def _faults(files: Files) -> dict[str, tuple[Path, Path, Path, Path]]:
    """Each fault: (ca, cert, key) and the file the error must name."""
    ca, server = files.ca.cert, files.server
    return {
        "missing CA": (files.missing, server.cert, server.key, files.missing),
        "CA not a certificate": (files.not_pem, server.cert, server.key, files.not_pem),
        "expired": (ca, files.expired.cert, files.expired.key, files.expired.cert),
        "not yet valid": (ca, files.future.cert, files.future.key, files.future.cert),
        "key of another certificate": (ca, server.cert, files.robot.key, server.cert),
    }


FAULTS = ["missing CA", "CA not a certificate", "expired", "not yet valid", "key of another certificate"]


def _one_error_line(out: Result, path: Path) -> str:
    assert out.exit_code == 2, out.output
    errors = [line for line in out.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, out.output
    assert str(path) in errors[0], errors[0]
    return errors[0]


@pytest.mark.parametrize("fault", FAULTS)
def test_serve_refuses_a_bad_tls_file_before_building_the_policy(files: Files, fault: str) -> None:
    ca, cert, key, named = _faults(files)[fault]
    tls = ["--tls-ca", str(ca), "--tls-cert", str(cert), "--tls-key", str(key)]
    # An unknown skill would be the error if anything after the TLS check ran.
    out = CliRunner().invoke(main.cli, ["serve", "--skill", "no_such_skill", *tls])
    line = _one_error_line(out, named)
    assert "--tls-" in line


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--mtls"], "--mtls needs TLS"),
        (["--tls-ca", "ca.crt"], "TLS needs --tls-cert, --tls-key too"),
        (["--allow", "robot-1"], "needs tls with mutual"),
    ],
)
def test_serve_refuses_tls_options_that_do_not_go_together(args: list[str], message: str) -> None:
    out = CliRunner().invoke(main.cli, ["serve", "--skill", "noop", *args])
    assert out.exit_code == 2, out.output
    assert message in out.output


def test_serve_with_tls_refuses_a_plain_endpoint_beside_it(files: Files) -> None:
    tls = ["--tls-ca", str(files.ca.cert), "--tls-cert", str(files.server.cert), "--tls-key", str(files.server.key)]
    out = CliRunner().invoke(main.cli, ["serve", "--skill", "noop", *tls, "--listen", "tcp/127.0.0.1:7447"])
    assert out.exit_code == 2, out.output
    assert "'tcp/127.0.0.1:7447' would be a plain link" in out.output


REMOTE = """
name: remote
rate_hz: 30
hal: {robot_id: so101_follower, adapter: null}
vla:
  id: remote_policy
  params:
    policy: nobody
    connect_timeout_s: 0.2
    zenoh:
      connect: [ENDPOINT]
      tls: {ca: "CA", cert: "CERT", key: "KEY", mutual: true}
safety: {client: envelope}
"""


@pytest.mark.parametrize("command", ["validate", "deploy"])
@pytest.mark.parametrize("fault", FAULTS)
def test_a_deployment_with_a_bad_tls_file_is_refused_before_connecting(
    files: Files, tmp_path: Path, fault: str, command: str
) -> None:
    ca, cert, key, named = _faults(files)[fault]
    endpoint = free_endpoint().replace("tcp/", "tls/", 1)
    text = REMOTE.replace("ENDPOINT", endpoint).replace("CA", str(ca)).replace("CERT", str(cert))
    path = tmp_path / "remote.yaml"
    path.write_text(text.replace("KEY", str(key)))
    args = ["validate", str(path)] if command == "validate" else ["deploy", "--config", str(path), "--duration", "0.1"]
    line = _one_error_line(CliRunner().invoke(main.cli, args), named)
    assert "vla.params.zenoh.tls." in line


def test_serve_with_mutual_tls_and_access_control_serves_only_the_allowed_robot(files: Files) -> None:
    endpoint = free_endpoint().replace("tcp/", "tls/", 1)
    server = files.server
    tls = ["--tls-ca", str(files.ca.cert), "--tls-cert", str(server.cert), "--tls-key", str(server.key)]
    command = [sys.executable, "-m", "openral_cli", "serve", "--skill", "noop", "--listen", endpoint, *tls]
    process = subprocess.Popen(
        [*command, "--mtls", "--allow", "robot-1"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    keys = PolicyKeys.of("so101_follower", "noop")

    def robot(issued: Issued) -> RemotePolicyClient:
        tls_block = TlsConfig(ca=str(files.ca.cert), cert=str(issued.cert), key=str(issued.key), mutual=True)
        return RemotePolicyClient(keys, ZenohConfig(connect=[endpoint], tls=tls_block))

    allowed, intruder = robot(files.robot), robot(files.intruder)
    try:
        meta = allowed.connect(timeout_s=60.0)
        assert meta.skill_id == "noop"
        with pytest.raises(ServerUnavailable):
            intruder.connect(timeout_s=3.0)
    finally:
        allowed.close()
        intruder.close()
        process.send_signal(signal.SIGINT)
        _out, err = process.communicate(timeout=60)
    assert process.returncode == 0, err
    assert f"mutual TLS, Zenoh id {allowed.server_id}" in err  # the id robots pin is the one it prints
