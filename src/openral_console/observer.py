"""``ConsoleObserver``: the live web console (observer ``console``, ``--console [HOST:]PORT``).

A person opens the printed URL to watch a running robot (every camera's thumbnail, measured and
commanded joints, the loop's health, the executor's state, the skill and task, the tick counter)
and to press the buttons the command registered (stop, next episode, re-record, ...).

On the tick thread it stores one reference per tick; thumbnails come from the runner's
``thumbnails`` observer (encoded once for every viewer) and are stored the same way. Everything
else (the health, JSON, the network) happens on the server's own thread
(:mod:`openral_console.server`). Building it opens nothing; :meth:`start` binds the port and
prints the URL on stderr; :meth:`close` tells open pages the run ended and releases the port.

A loopback bind (the default) needs no token. Any other bind makes a token at start: the printed
URL carries it, and every request without it is refused (:mod:`openral_console.auth`).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from typing import IO, Any

from openral_console.auth import TOKEN_PARAM, is_loopback, new_token
from openral_console.feed import ConsoleFeed
from openral_console.params import ConsoleParams
from openral_console.server import ConsoleServer, check_installed
from openral_core import ObserverContext, TickResult, WorldState
from openral_core.config import validate_model
from openral_observability.observer import Thumbnail, TickObserver

_WILDCARDS = frozenset({"0.0.0.0", "::", "[::]"})


class ConsoleObserver(TickObserver):
    """Serves the live console while the runner runs.

    Args:
        params: Host, port, rates and limits.
        option: The command-line option (or field) that configured it; errors name it.
        announce: Where the URL is printed at start (stderr by default).
    """

    def __init__(
        self,
        params: ConsoleParams | None = None,
        *,
        option: str = "observers[].params",
        announce: IO[str] | None = None,
    ) -> None:
        self.params = params or ConsoleParams()
        self.feed = ConsoleFeed()
        self._option = option
        self._announce = announce
        self.token: str | None = None
        """The token every request must carry, made at :meth:`start` on a non-loopback bind."""
        self._server: ConsoleServer | None = None
        self._closed = False

    @classmethod
    def from_config(cls, params: Mapping[str, Any], context: ObserverContext) -> ConsoleObserver:
        """Plugin constructor (observer ``console``); ``params`` are validated as :class:`ConsoleParams`.

        Opens nothing, but checks what :meth:`start` needs, so ``openral validate`` refuses what the run would.

        Raises:
            ROSConfigError: A wrong parameter (named with the allowed keys).
            ROSDependencyMissing: aiohttp is not installed (the ``console`` extra).
        """
        check_installed()
        field = context.option or "observers[].params"
        config = validate_model(ConsoleParams, dict(params), field_prefix=field)
        return cls(config, option=field)

    # -- what commands call ------------------------------------------------------------------

    def set_status(self, source: Callable[[], Mapping[str, Any]]) -> None:
        """Where the loop's health comes from (called on the server's thread, a few times a second)."""
        self.feed.status = source

    def register_control(self, name: str, action: Callable[[], object], *, label: str | None = None) -> None:
        """Show a button ``name`` on the page that runs ``action`` (on a worker thread) when pressed.

        Raises:
            ROSConfigError: ``name`` is not a short lower-case identifier.
        """
        self.feed.controls.register(name, action, label=label)

    @property
    def port(self) -> int | None:
        """The port the console listens on (the real one when 0 was asked), ``None`` before :meth:`start`."""
        return None if self._server is None else self._server.port

    @property
    def url(self) -> str | None:
        """The URL to open (with the token when one is needed), ``None`` before :meth:`start`."""
        port = self.port
        if port is None:
            return None
        host = self.params.host
        if host in _WILDCARDS:
            host = _this_host()
        if ":" in host and not host.startswith("["):
            host = f"[{host}]"
        query = "" if self.token is None else f"?{TOKEN_PARAM}={self.token}"
        return f"http://{host}:{port}/{query}"

    # -- observer lifecycle ----------------------------------------------------------------------

    def start(self) -> None:
        """Bind the port, serve, and print the URL on stderr. Idempotent.

        Raises:
            ROSConfigError: The address cannot be bound.
        """
        if self._server is not None or self._closed:
            return
        if not is_loopback(self.params.host):
            self.token = new_token()
        server = ConsoleServer(self.feed, self.params, token=self.token, option=self._option)
        server.start()
        self._server = server
        stream = self._announce if self._announce is not None else sys.stderr
        print(f"console: {self.url}", file=stream, flush=True)

    def on_tick(self, tick: TickResult, world: WorldState | None) -> None:
        """Keep a reference to the newest tick (tick thread; O(1))."""
        self.feed.put_tick(tick, world)

    def on_thumbnail(self, thumb: Thumbnail) -> None:
        """Keep the camera's newest thumbnail (the thumbnails observer's worker; O(1))."""
        self.feed.put_thumbnail(thumb)

    def on_episode_start(self, episode_idx: int, task: str) -> None:
        self.feed.episode = (episode_idx, task)

    def on_episode_end(self, episode_idx: int, *, success: bool, keep: bool = True) -> None:
        self.feed.episode = None

    def close(self) -> None:
        """Tell open pages the run ended and release the port. Idempotent; a later :meth:`start` does nothing."""
        self._closed = True
        if self._server is not None:
            self._server.close()


def _this_host() -> str:
    import socket  # noqa: PLC0415 (stdlib; only for a wildcard bind)

    return socket.gethostname()
