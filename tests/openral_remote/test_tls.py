"""TLS, mutual TLS and access control on a real link: a policy server in a child process, clients here.

Certificates are made in the test's folder (:mod:`openral_remote.testing_tls`). A refusal is only
meaningful once the server is known to be up, so each one follows a client that got through.
"""

from __future__ import annotations

import datetime as dt
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from openral_core import JointState, ROSConfigError, WorldState
from openral_remote.client import RemotePolicyClient, ServerUnavailable
from openral_remote.config import TlsConfig, ZenohConfig
from openral_remote.keys import PolicyKeys
from openral_remote.testing import ChunkSkill, free_endpoint
from openral_remote.testing_tls import Issued, make_ca, make_certificate
from openral_remote.tls import check_tls

pytestmark = pytest.mark.timeout(120)

SERVER, ROBOT, INTRUDER = "policy-server", "robot-1", "intruder"
REFUSAL_WAIT_S = 3.0
"""How long a refused client waits for the server (already known to be up) before giving up."""


@dataclass(frozen=True)
class Pki:
    ca: Issued
    server: Issued
    robot: Issued
    intruder: Issued
    foreign_ca: Issued
    foreign_robot: Issued
    both_cas: Path


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    folder = tmp_path_factory.mktemp("pki")
    ca = make_ca(folder)
    foreign = make_ca(folder / "foreign", "another CA")
    both = folder / "both-cas.crt"
    both.write_bytes(ca.cert.read_bytes() + foreign.cert.read_bytes())
    return Pki(
        ca=ca,
        server=make_certificate(folder, SERVER, ca),
        robot=make_certificate(folder, ROBOT, ca),
        intruder=make_certificate(folder, INTRUDER, ca),
        foreign_ca=foreign,
        foreign_robot=make_certificate(folder / "foreign", ROBOT, foreign),
        both_cas=both,
    )


def _world() -> WorldState:
    return WorldState(stamp_ns=1, joint_state=JointState(names=["a0", "a1"], positions=[0.1, -0.2]))


@pytest.fixture
def tls_endpoint() -> str:
    return free_endpoint().replace("tcp/", "tls/", 1)


@pytest.fixture
def tls_server(pki: Pki, tls_endpoint: str) -> Iterator[Callable[..., subprocess.Popen[bytes]]]:
    """Start ``python -m openral_remote.testing`` on ``tls_endpoint`` with the server's certificate."""
    started: list[subprocess.Popen[bytes]] = []

    def start(*args: str) -> subprocess.Popen[bytes]:
        command = [sys.executable, "-m", "openral_remote.testing", "--listen", tls_endpoint]
        command += ["--tls-ca", str(pki.ca.cert), "--tls-cert", str(pki.server.cert), "--tls-key", str(pki.server.key)]
        process = subprocess.Popen([*command, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        started.append(process)
        return process

    yield start
    for process in started:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)


@pytest.fixture
def connect(keys: PolicyKeys) -> Iterator[Callable[..., RemotePolicyClient]]:
    """Connect a client with ``zenoh``; closed at the end."""
    made: list[RemotePolicyClient] = []

    def open_client(zenoh: ZenohConfig, timeout_s: float = 20.0) -> RemotePolicyClient:
        remote = RemotePolicyClient(keys, zenoh, deadline_ms=2000)
        made.append(remote)
        remote.connect(timeout_s=timeout_s)
        return remote

    yield open_client
    for remote in made:
        remote.close()


def _robot(endpoint: str, issued: Issued | None, ca: Issued | Path, *, allow: tuple[str, ...] = ()) -> ZenohConfig:
    """A robot's session: TLS to ``endpoint`` trusting ``ca``, presenting ``issued`` (mutual) or no certificate."""
    trusted = str(ca if isinstance(ca, Path) else ca.cert)
    if issued is None:
        tls = TlsConfig(ca=trusted)
    else:
        tls = TlsConfig(ca=trusted, cert=str(issued.cert), key=str(issued.key), mutual=True)
    return ZenohConfig(connect=[endpoint], tls=tls, allow=list(allow))


# -- links ---------------------------------------------------------------------------------


def test_a_robot_with_a_valid_certificate_gets_chunks_over_mutual_tls(
    pki: Pki, tls_server, tls_endpoint: str, connect
) -> None:
    tls_server("--mtls")
    remote = connect(_robot(tls_endpoint, pki.robot, pki.ca))
    expected = ChunkSkill(["a0", "a1"]).rows(_world())
    np.testing.assert_array_equal(remote.infer(_world()), expected)
    remote.reset(seed=3)


def test_a_mutual_tls_server_refuses_a_robot_without_a_valid_certificate(
    pki: Pki, tls_server, tls_endpoint: str, connect
) -> None:
    tls_server("--mtls")
    connect(_robot(tls_endpoint, pki.robot, pki.ca))  # the server is up
    with pytest.raises(ServerUnavailable):  # no certificate at all
        connect(_robot(tls_endpoint, None, pki.ca), timeout_s=REFUSAL_WAIT_S)
    with pytest.raises(ServerUnavailable):  # a certificate of another authority (the robot trusts both), same name
        connect(_robot(tls_endpoint, pki.foreign_robot, pki.both_cas), timeout_s=REFUSAL_WAIT_S)


def test_a_plain_tcp_client_cannot_reach_a_tls_server(pki: Pki, tls_server, tls_endpoint: str, connect) -> None:
    tls_server()
    assert connect(_robot(tls_endpoint, None, pki.ca)).infer(_world()).shape == (10, 2)  # TLS without mutual: up
    plain = ZenohConfig(connect=[tls_endpoint.replace("tls/", "tcp/", 1)])
    with pytest.raises(ServerUnavailable):
        connect(plain, timeout_s=REFUSAL_WAIT_S)


def test_a_robot_that_does_not_trust_the_servers_authority_does_not_reach_it(
    pki: Pki, tls_server, tls_endpoint: str, connect
) -> None:
    tls_server()
    connect(_robot(tls_endpoint, None, pki.ca))  # the server is up
    with pytest.raises(ServerUnavailable):
        connect(_robot(tls_endpoint, None, pki.foreign_ca), timeout_s=REFUSAL_WAIT_S)


# -- access control ------------------------------------------------------------------------


def test_only_the_allowed_robot_may_query_a_server_with_access_control(
    pki: Pki, tls_server, tls_endpoint: str, connect
) -> None:
    tls_server("--mtls", "--allow", ROBOT)
    assert connect(_robot(tls_endpoint, pki.robot, pki.ca)).infer(_world()).shape == (10, 2)
    with pytest.raises(ServerUnavailable):  # a valid certificate of the same authority, another name
        connect(_robot(tls_endpoint, pki.intruder, pki.ca), timeout_s=REFUSAL_WAIT_S)


def test_a_robot_with_access_control_hears_only_the_named_server(
    pki: Pki, tls_server, tls_endpoint: str, connect
) -> None:
    tls_server("--mtls")
    assert connect(_robot(tls_endpoint, pki.robot, pki.ca, allow=(SERVER,))).infer(_world()).shape == (10, 2)
    with pytest.raises(ServerUnavailable):  # the same server, but not the name this robot expects
        connect(_robot(tls_endpoint, pki.robot, pki.ca, allow=("another-server",)), timeout_s=REFUSAL_WAIT_S)


# -- configuration -------------------------------------------------------------------------


def test_tls_settings_are_zenohs_keys(pki: Pki) -> None:
    tls = TlsConfig(ca=str(pki.ca.cert), cert=str(pki.robot.cert), key=str(pki.robot.key), mutual=True)
    settings = ZenohConfig(connect=["tls/10.0.0.5:7447"], tls=tls, allow=[SERVER], id="1f").settings()
    assert settings["id"] == "1f"
    assert settings["transport/link/tls/root_ca_certificate"] == str(pki.ca.cert)
    assert settings["transport/link/tls/enable_mtls"] is True
    assert settings["transport/link/tls/connect_certificate"] == str(pki.robot.cert)
    assert settings["transport/link/tls/listen_private_key"] == str(pki.robot.key)
    control = settings["access_control"]
    assert isinstance(control, dict)
    assert control["default_permission"] == "deny"
    assert control["subjects"] == [{"id": "openral-allowed", "cert_common_names": [SERVER]}]


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"connect": ["tls/10.0.0.5:7447"]}, "needs a tls block"),
        ({"connect": ["tcp/10.0.0.5:7447"], "tls": {"ca": "ca.crt"}}, "would be a plain link"),
        ({"listen": ["tls/0.0.0.0:7447"], "tls": {"ca": "ca.crt"}}, "needs tls.cert and tls.key"),
        ({"tls": {"ca": "ca.crt", "cert": "a.crt"}}, "cert and key go together"),
        ({"tls": {"ca": "ca.crt"}, "allow": ["robot-1"]}, "needs tls with mutual"),
        ({"allow": ["robot-1"]}, "needs tls with mutual"),
        ({"id": "0abc"}, "should match pattern"),
        ({"id": "ABC"}, "should match pattern"),
    ],
)
def test_a_security_setting_that_cannot_work_is_refused(fields: dict[str, object], message: str) -> None:
    from openral_core.config import validate_model  # noqa: PLC0415

    with pytest.raises(ROSConfigError, match=message):
        validate_model(ZenohConfig, fields)


# -- files ---------------------------------------------------------------------------------


def _bad_files(pki: Pki, folder: Path) -> dict[str, tuple[TlsConfig, Path, str]]:
    """Each fault: the TLS block, the file it must name, and the field."""
    now = dt.datetime.now(dt.UTC)
    a_day = dt.timedelta(days=1)
    expired = make_certificate(folder, "expired", pki.ca, valid_from=now - 2 * a_day, valid_until=now - a_day)
    future = make_certificate(folder, "future", pki.ca, valid_from=now + a_day)
    not_pem = folder / "not-a-certificate.crt"
    not_pem.write_text("just some text\n")
    encrypted = folder / "encrypted.key"
    from cryptography.hazmat.primitives import serialization  # noqa: PLC0415

    encrypted.write_bytes(
        pki.robot.private_key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.BestAvailableEncryption(b"secret"),
        )
    )
    ca, robot, missing = str(pki.ca.cert), pki.robot, folder / "missing.crt"
    foreign_with_ca = folder / "foreign-with-ca.crt"  # another CA's certificate, this CA's appended after it
    foreign_with_ca.write_bytes(pki.foreign_robot.cert.read_bytes() + pki.ca.cert.read_bytes())

    def block(ca: str = ca, cert: Path = robot.cert, key: Path = robot.key) -> TlsConfig:
        return TlsConfig(ca=ca, cert=str(cert), key=str(key))

    return {
        "missing": (block(cert=missing), missing, "cert"),
        "expired": (block(cert=expired.cert, key=expired.key), expired.cert, "cert"),
        "not yet valid": (block(cert=future.cert, key=future.key), future.cert, "cert"),
        "key of another certificate": (block(key=pki.intruder.key), robot.cert, "cert"),
        "CA not a certificate": (block(ca=str(not_pem)), not_pem, "ca"),
        "CA not the signer": (block(ca=str(pki.foreign_ca.cert)), robot.cert, "cert"),
        "CA appended to another CA's certificate": (
            block(cert=foreign_with_ca, key=pki.foreign_robot.key),
            foreign_with_ca,
            "cert",
        ),
        "key is a certificate": (block(key=robot.cert), robot.cert, "key"),
        "encrypted key": (block(key=encrypted), encrypted, "key"),
    }


@pytest.mark.parametrize(
    "fault",
    [
        "missing",
        "expired",
        "not yet valid",
        "key of another certificate",
        "CA not a certificate",
        "CA not the signer",
        "CA appended to another CA's certificate",
        "key is a certificate",
        "encrypted key",
    ],
)
def test_a_bad_tls_file_is_one_line_naming_it(pki: Pki, tmp_path: Path, fault: str) -> None:
    tls, path, field = _bad_files(pki, tmp_path)[fault]
    with pytest.raises(ROSConfigError) as caught:
        check_tls(tls)
    text = str(caught.value)
    assert "\n" not in text
    assert str(path) in text
    assert caught.value.field == f"zenoh.tls.{field}"


def test_good_tls_files_pass(pki: Pki) -> None:
    check_tls(TlsConfig(ca=str(pki.ca.cert), cert=str(pki.server.cert), key=str(pki.server.key)))
    check_tls(TlsConfig(ca=str(pki.ca.cert)))


def test_a_certificate_signed_by_an_intermediate_passes_only_with_the_intermediate_in_its_file(
    pki: Pki, tmp_path: Path
) -> None:
    upper = make_ca(tmp_path / "upper", "intermediate 1", issuer=pki.ca)
    lower = make_ca(tmp_path / "lower", "intermediate 2", issuer=upper)
    leaf = make_certificate(tmp_path, "leaf", lower)
    chain = tmp_path / "chain.crt"  # as a CA hands it out: the certificate first, intermediates in any order
    chain.write_bytes(leaf.cert.read_bytes() + upper.cert.read_bytes() + lower.cert.read_bytes())
    check_tls(TlsConfig(ca=str(pki.ca.cert), cert=str(chain), key=str(leaf.key)))
    check_tls(TlsConfig(ca=str(upper.cert), cert=str(chain), key=str(leaf.key)))  # an intermediate as the CA
    partial = tmp_path / "partial.crt"  # the link to the CA is missing
    partial.write_bytes(leaf.cert.read_bytes() + lower.cert.read_bytes())
    with pytest.raises(ROSConfigError, match="is not signed by the CA"):
        check_tls(TlsConfig(ca=str(pki.ca.cert), cert=str(partial), key=str(leaf.key)))
    not_an_authority = tmp_path / "by-a-leaf.crt"  # a certificate that is no CA cannot vouch for another
    signed_by_leaf = make_certificate(tmp_path / "by-leaf", "signed-by-leaf", leaf)
    not_an_authority.write_bytes(signed_by_leaf.cert.read_bytes() + leaf.cert.read_bytes())
    with pytest.raises(ROSConfigError, match="is not signed by the CA"):
        check_tls(TlsConfig(ca=str(lower.cert), cert=str(not_an_authority), key=str(signed_by_leaf.key)))
