"""Who tunes the allocator for camera-sized messages: ``serve``, and a remote policy's client; nothing else."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from openral_cli import main, serve
from openral_remote import skill
from openral_remote.testing import free_endpoint

LOCAL = """
name: local
rate_hz: 200
hal: {robot_id: so101_follower, adapter: null}
vla: {id: noop}
safety: {client: envelope}
"""

REMOTE = """
name: remote
rate_hz: 30
hal: {robot_id: so101_follower, adapter: null}
vla:
  id: remote_policy
  params: {policy: nobody, zenoh: {connect: [ENDPOINT]}, connect_timeout_s: 0.2}
safety: {client: envelope}
"""


@pytest.fixture
def tuned(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The commands that asked for the allocator tuning (recorded, not made)."""
    calls: list[str] = []
    monkeypatch.setattr(serve, "keep_message_memory", lambda: calls.append("serve") or True)
    monkeypatch.setattr(skill, "keep_message_memory", lambda: calls.append("remote_policy") or True)
    return calls


def test_serve_keeps_message_memory_before_it_builds_the_policy(tuned: list[str]) -> None:
    out = CliRunner().invoke(main.cli, ["serve", "--skill", "no_such_skill"])
    assert out.exit_code == 2, out.output  # the unknown skill is refused after the tuning
    assert tuned == ["serve"]


def test_deploy_on_a_remote_policy_keeps_message_memory(tuned: list[str], tmp_path: Path) -> None:
    path = tmp_path / "remote.yaml"
    path.write_text(REMOTE.replace("ENDPOINT", free_endpoint()))
    out = CliRunner().invoke(main.cli, ["deploy", "--config", str(path), "--duration", "0.1"])
    assert out.exit_code == 1, out.output  # no server answers: a run-time failure, after the tuning
    assert tuned == ["remote_policy"]


def test_deploy_on_a_local_skill_leaves_the_allocator_alone(tuned: list[str], tmp_path: Path) -> None:
    path = tmp_path / "local.yaml"
    path.write_text(LOCAL)
    out = CliRunner().invoke(main.cli, ["deploy", "--config", str(path), "--duration", "0.1"])
    assert out.exit_code == 0, out.output
    assert tuned == []
