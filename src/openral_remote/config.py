"""Settings of a Zenoh session and of a remote policy, validated like the rest of a deployment file.

Defaults are chosen for a LAN: peers find each other only through the endpoints given (no
multicast scouting), and a link that goes silent is declared dead after ``lease_ms`` (1 s, not
Zenoh's 10 s), which is what bounds how long a robot acts on a server that vanished without a word.
"""

from __future__ import annotations

import re
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

DEFAULT_PORT = 7447
DEFAULT_SERVER_LISTEN = f"tcp/0.0.0.0:{DEFAULT_PORT}"
DEFAULT_CLIENT_CONNECT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

_ENDPOINT = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream|unixpipe|serial|vsock)/\S+$")


def _check_endpoints(values: list[str]) -> list[str]:
    for value in values:
        if not _ENDPOINT.match(value):
            raise ValueError(f"{value!r} is not a Zenoh endpoint; write e.g. 'tcp/192.168.1.20:{DEFAULT_PORT}'")
    return values


class ZenohConfig(BaseModel):
    """One Zenoh session: how it finds peers and how fast it notices one is gone."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mode: Literal["peer", "client"] = Field(default="peer", description="peer: direct links; client: via a router.")
    connect: list[str] = Field(default_factory=list, description="Endpoints to connect to, e.g. tcp/10.0.0.5:7447.")
    listen: list[str] = Field(default_factory=list, description="Endpoints to listen on, e.g. tcp/0.0.0.0:7447.")
    lease_ms: int = Field(
        default=1000, ge=100, le=60_000, description="A silent link is declared dead after this long (Zenoh: 10 s)."
    )
    multicast_scouting: bool = Field(default=False, description="Find peers by multicast (off: endpoints only).")
    shared_memory: bool = Field(default=True, description="Use shared memory with peers on the same host.")

    _endpoints = field_validator("connect", "listen")(_check_endpoints)

    def settings(self) -> dict[str, object]:
        """Zenoh configuration paths → values (JSON5), as ``zenoh.Config.insert_json5`` takes them."""
        return {
            "mode": self.mode,
            "connect/endpoints": list(self.connect),
            "listen/endpoints": list(self.listen),
            "scouting/multicast/enabled": self.multicast_scouting,
            "transport/link/tx/lease": self.lease_ms,
            "transport/shared_memory/enabled": self.shared_memory,
        }


class RemotePolicyParams(BaseModel):
    """``params`` of the ``remote_policy`` skill: which server, how long to wait, what a changed model means."""

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
    jpeg_quality: int | None = Field(
        default=None, ge=1, le=95, description="Send camera images as JPEG of this quality (slow links); raw if unset."
    )
