"""``--console [HOST:]PORT``: the live web console of ``deploy``, ``record`` and ``sim run``.

The option stands for a ``console`` observer entry (plus the ``thumbnails`` observer, so the page
shows the cameras). Once the runner is up, :func:`attach_console` hands the console its status
source and the buttons the command supports. ``openral_console`` (aiohttp) is loaded only when
the option is given.
"""

from __future__ import annotations

import ipaddress
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import click

from openral_cli.recording import WatchedT, with_observers, with_thumbnails
from openral_core import ObserverConfig
from openral_observability.observer import TickObserver

CONSOLE_OBSERVER = "console"
CONSOLE_IMAGE_HZ = 10.0
"""Camera thumbnails per second for the console when the deployment sets no ``thumbnail_hz``."""
_OPTION = "--console"


@dataclass(frozen=True)
class ConsoleAddress:
    """Where ``--console`` serves: loopback unless a host is given."""

    host: str
    port: int


class ConsoleAddressType(click.ParamType):  # type: ignore[type-arg]
    """``PORT``, ``HOST:PORT`` or ``[IPv6]:PORT``; port 0 picks a free one."""

    name = "[HOST:]PORT"

    def convert(self, value: object, param: click.Parameter | None, ctx: click.Context | None) -> ConsoleAddress:
        if isinstance(value, ConsoleAddress):
            return value
        text = str(value).strip()
        host, sep, port_text = text.rpartition(":")
        if not sep:
            host = "127.0.0.1"
        elif host.startswith("[") and host.endswith("]"):
            host = host[1:-1]
            try:
                ipaddress.IPv6Address(host)
            except ValueError:
                self.fail(f"{text!r}: {host!r} is not an IPv6 address", param, ctx)
        elif ":" in host:
            self.fail(f"{text!r}: write an IPv6 host in brackets, e.g. [::1]:8080", param, ctx)
        if sep and not host:
            self.fail(f"{text!r} has no host before ':'; give PORT alone for loopback, e.g. 8080", param, ctx)
        if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
            self.fail(
                f"{text!r}: the port must be a number from 0 to 65535 (0: any free port), e.g. 8080 or 0.0.0.0:8080",
                param,
                ctx,
            )
        return ConsoleAddress(host, int(port_text))


CONSOLE_OPTION = click.option(
    "--console",
    "console",
    type=ConsoleAddressType(),
    default=None,
    metavar="[HOST:]PORT",
    help="Serve a live web console (cameras, joints, loop health, stop and other buttons) on this port "
    "(0: any free one); loopback unless HOST is given, and then only with the token printed at start.",
)


def console_entry(address: ConsoleAddress) -> ObserverConfig:
    """The ``console`` observer entry ``--console`` stands for."""
    return ObserverConfig.shorthand(CONSOLE_OBSERVER, {"host": address.host, "port": address.port}, option=_OPTION)


def with_console(env: WatchedT, address: ConsoleAddress | None) -> WatchedT:
    """``env`` (a deployment or a scene) with the console and a ``thumbnails`` observer for its cameras.

    Unchanged without ``--console``.
    """
    if address is None:
        return env
    return with_observers(with_thumbnails(env, CONSOLE_IMAGE_HZ), console_entry(address))


def attach_console(runner: Any, **controls: Callable[[], object]) -> None:
    """Give every console among ``runner.observers`` the runner's health and the buttons ``controls`` name.

    ``runner`` is a started runner (hardware or simulation); each keyword is a control name
    (``stop``, ``next``, ``rerecord``, ``takeover``, ``highlight``) and the action its button runs.
    Does nothing when the runner has no console.
    """
    consoles = consoles_of(runner.observers)
    if not consoles:
        return
    from openral_console.status import runner_status  # noqa: PLC0415 - with --console only

    def health() -> Any:
        return runner_status(runner)

    for console in consoles:
        console.set_status(health)
        for name, action in controls.items():
            console.register_control(name, action)


def consoles_of(observers: Sequence[TickObserver]) -> list[Any]:
    """The consoles among ``observers``; none (and nothing loaded) when the console module was never imported."""
    module = sys.modules.get("openral_console.observer")
    if module is None:
        return []
    return [o for o in observers if isinstance(o, module.ConsoleObserver)]
