"""Server identity pinning: a robot acts only on the server it first reached (its Zenoh id).

A peer that copied the public ``meta`` (model hash included) and declares ``alive`` and ``infer``
after the real server went away is refused; the real server, back under its stable id, is taken back.
"""

from __future__ import annotations

import pytest

from openral_core import JointState, ROSConfigError, WorldState
from openral_core.config import validate_model
from openral_remote.client import RemotePolicyClient, ServerRefused, ServerUnavailable
from openral_remote.config import RemotePolicyParams, ZenohConfig
from openral_remote.testing import wait_for

pytestmark = pytest.mark.timeout(120)

IMPOSTOR_ID = "1badc0de"


def _world() -> WorldState:
    return WorldState(stamp_ns=1, joint_state=JointState(names=["a0", "a1"], positions=[0.1, -0.2]))


def test_an_impostor_with_the_public_meta_is_refused_and_the_real_server_is_taken_back(server, client, keys) -> None:
    real = server()
    remote = client()
    real_id = remote.server_id
    remote.infer(_world())
    real.stop()
    assert wait_for(lambda: not remote.available(), timeout_s=5.0)
    # Same key, same meta (the model hash is public), its own alive token and infer queryable: another id.
    impostor = server("--zenoh-id", IMPOSTOR_ID)
    assert wait_for(lambda: remote.changes[-1:] == ["refused"])
    assert not remote.available()  # the executor's fallback keeps acting
    with pytest.raises(ServerUnavailable):
        remote.infer(_world())
    impostor.stop()
    server()  # the real server again, under the id it keeps on this host
    assert wait_for(remote.available)
    assert remote.changes == ["down", "refused", "up"]
    assert remote.server_id == real_id
    assert remote.infer(_world()).shape == (10, 2)


def test_a_reply_from_another_server_than_the_pinned_one_is_not_acted_on(server, client) -> None:
    server()
    remote = client(server_id=None)
    real_id = remote.server_id
    remote.server_id = IMPOSTOR_ID  # as if the pinned server were another: the replies now come from a stranger
    with pytest.raises(ServerRefused, match=f"answered by Zenoh id {real_id}, not the pinned server {IMPOSTOR_ID}"):
        remote.infer(_world())
    assert not remote.available()
    assert wait_for(lambda: remote.changes == ["down", "refused"])  # its meta, read again, is a stranger's too
    assert not remote.available()


def test_a_server_id_pinned_up_front_refuses_another_server_at_start(server, client, keys, client_zenoh) -> None:
    server()
    real_id = client().server_id  # what 'openral serve' prints
    remote = RemotePolicyClient(keys, client_zenoh, server_id=IMPOSTOR_ID)
    with pytest.raises(ROSConfigError, match=f"not the pinned server {IMPOSTOR_ID}"):
        remote.connect(timeout_s=20.0)
    assert not remote.available()
    pinned = RemotePolicyClient(keys, client_zenoh, server_id=real_id)
    try:
        pinned.connect(timeout_s=20.0)
        assert pinned.infer(_world()).shape == (10, 2)
    finally:
        pinned.close()


def test_accepting_a_server_change_pins_the_new_server(server, client) -> None:
    first = server()
    remote = client(on_server_change="accept")
    first.stop()
    assert wait_for(lambda: not remote.available(), timeout_s=5.0)
    server("--zenoh-id", IMPOSTOR_ID)
    assert wait_for(remote.available)
    assert remote.server_id == IMPOSTOR_ID
    assert remote.changes == ["down", "up"]
    assert remote.infer(_world()).shape == (10, 2)


def test_pinning_an_id_and_accepting_any_other_is_refused() -> None:
    with pytest.raises(ROSConfigError, match="server_id pins one server"):
        validate_model(RemotePolicyParams, {"policy": "p", "server_id": IMPOSTOR_ID, "on_server_change": "accept"})
    with pytest.raises(ROSConfigError, match="server_id"):
        validate_model(RemotePolicyParams, {"policy": "p", "server_id": "not-hex"})


def test_the_skill_refuses_at_start_a_server_other_than_the_one_it_was_built_for(server, keys, endpoint) -> None:
    from openral_core import ROSSkillError  # noqa: PLC0415
    from openral_hal.manifests import load_robot_manifest  # noqa: PLC0415
    from openral_remote.skill import RemotePolicySkill  # noqa: PLC0415

    real = server("--dims", "6")
    params = RemotePolicyParams(
        policy=keys.policy, robot=keys.robot, zenoh=ZenohConfig(connect=[endpoint]), connect_timeout_s=20
    )
    skill = RemotePolicySkill(load_robot_manifest("so101_follower"), params, rate_hz=10.0)
    assert skill.server_id is not None
    real.stop()
    server("--dims", "6", "--zenoh-id", IMPOSTOR_ID)  # the same meta, another id, between build and start
    with pytest.raises(ROSSkillError) as caught:
        skill.configure()
    assert isinstance(caught.value.__cause__, ROSConfigError)
    assert f"not the pinned server {skill.server_id}" in str(caught.value.__cause__)
