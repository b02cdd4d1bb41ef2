"""A server's Zenoh id: kept across restarts on a host, never shared by two live servers of the host."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from openral_core import ROSConfigError
from openral_remote.config import ZENOH_ID
from openral_remote.identity import claim_server_id, state_folder
from openral_remote.keys import PolicyKeys

KEYS = PolicyKeys.of("so101_follower", "hello")


def test_a_restart_takes_the_same_id_and_a_second_live_server_another(tmp_path: Path) -> None:
    with claim_server_id(KEYS, folder=tmp_path) as first:
        assert re.fullmatch(ZENOH_ID, first.zid)
        with claim_server_id(KEYS, folder=tmp_path) as second:
            assert second.zid != first.zid
        kept = first.zid
    with claim_server_id(KEYS, folder=tmp_path) as restarted:
        assert restarted.zid == kept
    with claim_server_id(PolicyKeys.of("so101_follower", "other"), folder=tmp_path) as other_key:
        assert other_key.zid != kept


def test_another_process_holding_the_id_gets_none_of_it(tmp_path: Path) -> None:
    code = (
        "import sys; from pathlib import Path\n"
        "from openral_remote.identity import claim_server_id\n"
        "from openral_remote.keys import PolicyKeys\n"
        "claim = claim_server_id(PolicyKeys.of('so101_follower', 'hello'), folder=Path(sys.argv[1]))\n"
        "print(claim.zid, flush=True)\n"
        "sys.stdin.read()\n"  # held until the test closes its input
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", code, str(tmp_path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None
        held = holder.stdout.readline().strip()  # the claim is made: the process holds the lock
        with claim_server_id(KEYS, folder=tmp_path) as mine:
            assert mine.zid != held
    finally:
        holder.communicate(timeout=30)
    with claim_server_id(KEYS, folder=tmp_path) as after:  # the holder is gone: its id is free again
        assert after.zid == held


def test_an_id_given_by_hand_is_held_by_one_server_of_the_host(tmp_path: Path) -> None:
    with claim_server_id(KEYS, "1f", folder=tmp_path) as given:
        assert given.zid == "1f"
        with pytest.raises(ROSConfigError, match="Zenoh id 1f is held by another policy server on this host"):
            claim_server_id(PolicyKeys.of("another", "policy"), "1f", folder=tmp_path)
    claim_server_id(KEYS, "1f", folder=tmp_path).close()


@pytest.mark.parametrize("zid", ["0abc", "ABC", "../x", "1f\n"])
def test_a_malformed_id_is_refused_before_any_file(tmp_path: Path, zid: str) -> None:
    with pytest.raises(ROSConfigError, match="is not a Zenoh id"):
        claim_server_id(KEYS, zid, folder=tmp_path / "state")
    assert not any((tmp_path / "state").glob("zid-*"))


def test_a_damaged_id_file_is_replaced(tmp_path: Path) -> None:
    with claim_server_id(KEYS, folder=tmp_path) as first:
        first.path.write_text("not an id\n")
    with claim_server_id(KEYS, folder=tmp_path) as second:
        assert re.fullmatch(ZENOH_ID, second.zid)
        assert second.path.read_text() == f"{second.zid}\n"


def test_a_folder_that_cannot_be_written_is_one_line_with_the_fix(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ROSConfigError, match=r"XDG_STATE_HOME: cannot keep the server's Zenoh id in .*give --zenoh-id"):
        claim_server_id(KEYS, folder=blocker / "serve")


def test_the_state_folder_follows_xdg_state_home(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    assert state_folder() == tmp_path / "openral" / "serve"
    monkeypatch.delenv("XDG_STATE_HOME")
    assert state_folder() == Path.home() / ".local" / "state" / "openral" / "serve"
