"""Settings of a Zenoh session and of a remote policy, validated like the rest of a deployment file.

Defaults are chosen for a LAN: peers find each other only through the endpoints given (no
multicast scouting), and a link that goes silent is declared dead after ``lease_ms`` (1 s, not
Zenoh's 10 s), which is what bounds how long a robot acts on a server that vanished without a word.

Security is opt-in and all-or-nothing per session: with a ``tls`` block every endpoint is a
``tls/`` one (no plain link is left open beside it), and ``allow`` turns on Zenoh's access control
so that only peers presenting a certificate with one of the listed common names are heard at all.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal, Self

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

DEFAULT_PORT = 7447
DEFAULT_SERVER_LISTEN = f"tcp/0.0.0.0:{DEFAULT_PORT}"
DEFAULT_SERVER_LISTEN_TLS = f"tls/0.0.0.0:{DEFAULT_PORT}"
DEFAULT_CLIENT_CONNECT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

ZENOH_ID = r"^[1-9a-f][0-9a-f]{0,31}$"
"""A Zenoh id as its configuration takes it: lowercase hex, 1 to 32 digits, no leading zero."""

_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream|unixpipe|serial|vsock)/\S+$")
_ACL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
)
"""Every message kind Zenoh's access control filters: an allowed peer may use them all, any other none."""


def _check_endpoints(values: list[str]) -> list[str]:
    for value in values:
        if not _ENDPOINT.match(value):
            raise ValueError(f"{value!r} is not a Zenoh endpoint; write e.g. 'tcp/192.168.1.20:{DEFAULT_PORT}'")
    return values


class TlsConfig(BaseModel):
    """Zenoh's TLS transport: the authority that signs every certificate, and this side's own.

    Paths are taken as given (``~`` expanded; a relative one from the working directory). Keys
    must be unencrypted PEM (Zenoh reads them without a passphrase).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    ca: str = Field(min_length=1, description="PEM certificate of the authority that signed the peers' certificates.")
    cert: str | None = Field(
        default=None, description="This side's PEM certificate: a server's always, a robot's under mutual TLS."
    )
    key: str | None = Field(default=None, description="The unencrypted PEM private key of cert.")
    mutual: bool = Field(
        default=False,
        description="Both sides present a certificate signed by ca; a listener refuses a peer without one.",
    )
    verify_name: bool = Field(
        default=True, description="A connecting side checks that the server's certificate names the host it dialled."
    )

    @model_validator(mode="after")
    def _pairs(self) -> Self:
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together: give both or neither")
        if self.mutual and self.cert is None:
            raise ValueError("mutual TLS needs this side's cert and key")
        return self

    def settings(self) -> dict[str, object]:
        """Zenoh configuration paths → values (the same certificate serves listening and connecting)."""
        out: dict[str, object] = {
            "transport/link/tls/root_ca_certificate": _path(self.ca),
            "transport/link/tls/enable_mtls": self.mutual,
            "transport/link/tls/verify_name_on_connect": self.verify_name,
        }
        if self.cert is not None and self.key is not None:
            for side in ("listen", "connect"):
                out[f"transport/link/tls/{side}_certificate"] = _path(self.cert)
                out[f"transport/link/tls/{side}_private_key"] = _path(self.key)
        return out


class ZenohConfig(BaseModel):
    """One Zenoh session: how it finds peers, how fast it notices one is gone, who it is and whom it trusts."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mode: Literal["peer", "client"] = Field(default="peer", description="peer: direct links; client: via a router.")
    connect: list[str] = Field(default_factory=list, description="Endpoints to connect to, e.g. tcp/10.0.0.5:7447.")
    listen: list[str] = Field(default_factory=list, description="Endpoints to listen on, e.g. tcp/0.0.0.0:7447.")
    lease_ms: int = Field(
        default=1000, ge=100, le=60_000, description="A silent link is declared dead after this long (Zenoh: 10 s)."
    )
    multicast_scouting: bool = Field(default=False, description="Find peers by multicast (off: endpoints only).")
    shared_memory: bool = Field(default=True, description="Use shared memory with peers on the same host.")
    id: str | None = Field(
        default=None,
        pattern=ZENOH_ID,
        description="This session's Zenoh id (lowercase hex, up to 32 digits, no leading 0); random when unset.",
    )
    tls: TlsConfig | None = Field(default=None, description="Encrypt and authenticate every link with TLS.")
    allow: list[str] = Field(
        default_factory=list,
        description="Certificate common names of the only peers this session exchanges anything with "
        "(Zenoh access control; needs tls with mutual: true). Empty: no access control.",
    )

    _endpoints = field_validator("connect", "listen")(_check_endpoints)

    @model_validator(mode="after")
    def _security(self) -> Self:
        endpoints = [*self.connect, *self.listen]
        if self.tls is None:
            secure = [endpoint for endpoint in endpoints if endpoint.startswith("tls/")]
            if secure:
                raise ValueError(f"endpoint {secure[0]!r} needs a tls block (ca, cert, key)")
        else:
            plain = [endpoint for endpoint in endpoints if not endpoint.startswith("tls/")]
            if plain:
                raise ValueError(
                    f"with tls on, every endpoint is a tls/ one; {plain[0]!r} would be a plain link beside it"
                )
            if self.listen and self.tls.cert is None:
                raise ValueError("a session that listens with TLS needs tls.cert and tls.key")
        if self.allow and (self.tls is None or not self.tls.mutual):
            raise ValueError("allow names peers by their certificates: it needs tls with mutual: true")
        if any(not name.strip() for name in self.allow):
            raise ValueError("allow lists certificate common names; an empty one would match anybody")
        return self

    def settings(self) -> dict[str, object]:
        """Zenoh configuration paths → values (JSON5), as ``zenoh.Config.insert_json5`` takes them."""
        out: dict[str, object] = {
            "mode": self.mode,
            "connect/endpoints": list(self.connect),
            "listen/endpoints": list(self.listen),
            "scouting/multicast/enabled": self.multicast_scouting,
            "transport/link/tx/lease": self.lease_ms,
            "transport/shared_memory/enabled": self.shared_memory,
        }
        if self.id is not None:
            out["id"] = self.id
        if self.tls is not None:
            out.update(self.tls.settings())
        if self.allow:
            out["access_control"] = access_control(self.allow)
        return out


def access_control(common_names: list[str]) -> dict[str, object]:
    """Zenoh's ``access_control`` block: peers with these certificate names may do anything, others nothing.

    Applied by each session to its own links, in both directions: on a server it means only the
    listed robots may query (or be answered), on a robot that only the listed server is heard.
    """
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {
                "id": "openral-peers",
                "messages": list(_ACL_MESSAGES),
                "flows": ["ingress", "egress"],
                "permission": "allow",
                "key_exprs": ["**"],
            }
        ],
        "subjects": [{"id": "openral-allowed", "cert_common_names": list(common_names)}],
        "policies": [{"rules": ["openral-peers"], "subjects": ["openral-allowed"]}],
    }


def _path(value: str) -> str:
    return str(Path(value).expanduser())


class RemotePolicyParams(BaseModel):
    """``params`` of the ``remote_policy`` skill: which server, how long to wait, what a change of it means."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    policy: str = Field(min_length=1, description="The served policy's name (the server's --name, default its skill).")
    robot: str | None = Field(default=None, description="The robot segment of the key; default: this robot's id.")
    zenoh: ZenohConfig = Field(default_factory=lambda: ZenohConfig(connect=[DEFAULT_CLIENT_CONNECT]))
    deadline_ms: float = Field(
        default=500.0, gt=0, le=60_000, description="A request without a reply by then is late (counted, dropped)."
    )
    connect_timeout_s: float = Field(
        default=10.0, gt=0, le=600, description="How long start-up waits for the server to be alive."
    )
    on_model_change: Literal["refuse", "accept"] = Field(
        default="refuse",
        description="A server that comes back with another model: refuse (stay on the fallback) or accept it.",
    )
    server_id: str | None = Field(
        default=None,
        pattern=ZENOH_ID,
        description="The server's Zenoh id ('openral serve' prints it), pinned up front; "
        "default: the id of the server first reached.",
    )
    on_server_change: Literal["refuse", "accept"] = Field(
        default="refuse",
        description="A server answering with another Zenoh id than the pinned one: refuse (stay on the "
        "fallback) or accept it (and pin the new id).",
    )
    jpeg_quality: int | None = Field(
        default=None, ge=1, le=95, description="Send camera images as JPEG of this quality (slow links); raw if unset."
    )

    @model_validator(mode="after")
    def _one_pin(self) -> Self:
        if self.server_id is not None and self.on_server_change == "accept":
            raise ValueError("server_id pins one server; on_server_change: accept would take any other")
        return self
