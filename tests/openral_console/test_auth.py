"""Who may reach the console: loopback binds trust this machine; any other needs the start-up token."""

from __future__ import annotations

import pytest

from openral_console.auth import foreign_origin, host_header_ok, is_loopback, new_token, token_status


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("127.0.0.1", True),
        ("127.0.0.2", True),
        ("localhost", True),
        ("::1", True),
        ("[::1]", True),
        ("0.0.0.0", False),
        ("::", False),
        ("192.168.1.20", False),
        ("robot.local", False),
    ],
)
def test_only_loopback_addresses_count_as_loopback(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_no_token_is_needed_when_none_is_expected() -> None:
    assert token_status(None, None, None) is None


def test_a_missing_token_is_401_a_wrong_one_403_the_right_one_passes() -> None:
    token = new_token()
    assert token_status(token, None, None) == 401
    assert token_status(token, "", None) == 401
    assert token_status(token, "nope", None) == 403
    assert token_status(token, token[:-1], None) == 403
    assert token_status(token, "é" + token, None) == 403  # non-ASCII does not crash the comparison
    assert token_status(token, token, None) is None
    assert token_status(token, None, f"Bearer {token}") is None
    assert token_status(token, None, "Bearer wrong") == 403
    assert token_status(token, None, f"Basic {token}") == 401


def test_tokens_are_fresh_and_long() -> None:
    assert new_token() != new_token()
    assert len(new_token()) >= 40


def test_another_sites_page_is_foreign_the_console_itself_is_not() -> None:
    assert not foreign_origin(None, "127.0.0.1:8080")
    assert not foreign_origin("http://127.0.0.1:8080", "127.0.0.1:8080")
    assert foreign_origin("http://evil.example", "127.0.0.1:8080")
    assert foreign_origin("http://127.0.0.1:9999", "127.0.0.1:8080")
    assert foreign_origin("null", "127.0.0.1:8080")


def test_a_rebinding_host_name_is_refused_on_loopback() -> None:
    assert host_header_ok("127.0.0.1:8080")
    assert host_header_ok("localhost:8080")
    assert host_header_ok("[::1]:8080")
    assert not host_header_ok("evil.example:8080")
    assert not host_header_ok(None)
    assert not host_header_ok("")
