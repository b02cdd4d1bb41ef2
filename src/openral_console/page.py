"""The console's page: one HTML document with its script and style inlined, and the headers it is served with.

The files ship as package data (``static/``); nothing is fetched from elsewhere, so the page works
offline. Inlining means the page is one request (which carries the token) and lets the
Content-Security-Policy allow exactly these two inline blocks by hash: no other script runs.
"""

from __future__ import annotations

import base64
import hashlib
from dataclasses import dataclass
from importlib import resources

_SCRIPT = "/*@console.js@*/"
_STYLE = "/*@console.css@*/"


@dataclass(frozen=True)
class Page:
    """The rendered page and its Content-Security-Policy."""

    html: bytes
    csp: str


def _digest(text: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(text.encode()).digest()).decode() + "'"


def load_page() -> Page:
    """Read the page's files from the package and inline the script and the style."""
    static = resources.files("openral_console") / "static"
    template = (static / "index.html").read_text(encoding="utf-8")
    script = (static / "console.js").read_text(encoding="utf-8")
    style = (static / "console.css").read_text(encoding="utf-8")
    html = template.replace(_SCRIPT, script).replace(_STYLE, style)
    csp = (
        "default-src 'none'; "
        f"script-src {_digest(script)}; style-src {_digest(style)}; "
        "img-src 'self' blob: data:; connect-src 'self'; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )
    return Page(html.encode(), csp)


SECURITY_HEADERS = {
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",  # the token is in the page's URL: never pass it on
    "Cache-Control": "no-store",
}
"""Sent with every response."""
