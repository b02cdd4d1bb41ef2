"""Who may open the console: loopback binds trust this machine, any other bind needs the start-up token.

The token is made with :mod:`secrets` when the server starts, printed once on stderr inside the
console's URL, and compared in constant time on every request (page, files, API, WebSocket).
Missing is 401, wrong is 403. Independently of the token, a request that a web page in the
operator's browser makes on its own (another site's script, a rebinding DNS name) is refused:
its ``Origin`` must be the console itself, and on a loopback bind its ``Host`` must name
loopback.
"""

from __future__ import annotations

import hmac
import ipaddress
import secrets
from urllib.parse import urlsplit

TOKEN_PARAM = "token"
"""The query parameter that carries the token (the page passes it on to its WebSocket and POSTs)."""

_LOOPBACK_NAMES = frozenset({"localhost", "localhost.", "ip6-localhost"})


def is_loopback(host: str) -> bool:
    """Whether binding ``host`` exposes the console to this machine only."""
    name = host.strip("[]").lower()
    if name in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def new_token() -> str:
    """A fresh URL-safe token (256 bits)."""
    return secrets.token_urlsafe(32)


def token_status(expected: str | None, query: str | None, authorization: str | None) -> int | None:
    """The HTTP status that refuses a request, ``None`` when it may proceed.

    Args:
        expected: The server's token; ``None`` on a loopback bind (nothing is checked).
        query: The ``token`` query parameter, if any.
        authorization: The ``Authorization`` header, if any (``Bearer <token>``).

    Returns:
        401 without a token, 403 with a wrong one.
    """
    if expected is None:
        return None
    given = query
    if given is None and authorization is not None:
        scheme, _, value = authorization.partition(" ")
        if scheme.lower() == "bearer":
            given = value.strip()
    if not given:
        return 401
    if not hmac.compare_digest(given.encode("utf-8", "surrogateescape"), expected.encode("utf-8")):
        return 403
    return None


def foreign_origin(origin: str | None, host: str | None) -> bool:
    """Whether a browser sent the request from a page that is not the console (``Origin`` ≠ the request's host)."""
    if origin is None:
        return False  # not a browser's cross-site request (curl, the page's own GET)
    try:
        netloc = urlsplit(origin).netloc
    except ValueError:
        return True
    return not netloc or host is None or netloc.lower() != host.lower()


def host_header_ok(host_header: str | None) -> bool:
    """On a loopback bind: whether the ``Host`` header names loopback (a rebinding DNS name does not)."""
    if not host_header:
        return False
    try:
        hostname = urlsplit(f"//{host_header}").hostname
    except ValueError:
        return False
    return hostname is not None and is_loopback(hostname)
