"""Recording keys read from the terminal: works over SSH, needs no X11 and no keyboard library.

On a terminal, stdin is put in cbreak mode for the command (each key arrives at once, unechoed)
and restored on exit; from a pipe the same characters are read as they come. ``n`` or → ends the
episode early (or the reset), ``r`` or ← re-records it, ``q`` or Esc stops recording. A command may
add its own keys: the takeover key (``t`` by default) passes control between the policy and a
person, ``s`` saves a highlight.
"""

from __future__ import annotations

import contextlib
import os
import select
import sys
import termios
import threading
import tty
from collections.abc import Callable, Mapping
from enum import StrEnum
from types import TracebackType
from typing import IO, Any, Self


class KeyCommand(StrEnum):
    NEXT = "next"
    RERECORD = "rerecord"
    STOP = "stop"
    TAKEOVER = "takeover"
    HIGHLIGHT = "highlight"


_SEQUENCES: dict[bytes, KeyCommand] = {
    b"\x1b[C": KeyCommand.NEXT,
    b"\x1b[D": KeyCommand.RERECORD,
    b"n": KeyCommand.NEXT,
    b"r": KeyCommand.RERECORD,
    b"q": KeyCommand.STOP,
    b"\x1b": KeyCommand.STOP,
}


def parse_keys(data: bytes, extra: Mapping[str, KeyCommand] | None = None) -> list[KeyCommand]:
    """The commands in a chunk read from the terminal (arrow keys are escape sequences).

    Args:
        extra: A command's own keys (one character each) beside the recording keys.
    """
    sequences = dict(_SEQUENCES)
    for key, command in (extra or {}).items():
        sequences[key.encode()] = command
    commands = []
    i = 0
    while i < len(data):
        for sequence in sorted(sequences, key=len, reverse=True):
            if data.startswith(sequence, i):
                commands.append(sequences[sequence])
                i += len(sequence)
                break
        else:
            i += 1
    return commands


class KeyReader:
    """Reads key commands from ``stream`` on a thread and hands each to ``on_command``.

    Args:
        on_command: Called on the reader thread with each command.
        stream: Where keys come from (stdin by default).
        extra: The command's own keys (one character each) beside the recording keys.
    """

    def __init__(
        self,
        on_command: Callable[[KeyCommand], None],
        stream: IO[Any] | None = None,
        *,
        extra: Mapping[str, KeyCommand] | None = None,
    ) -> None:
        self._on_command = on_command
        self._extra = dict(extra or {})
        self._stream = stream if stream is not None else sys.stdin
        self._saved: list[Any] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fd = -1

    def __enter__(self) -> Self:
        try:
            self._fd = self._stream.fileno()
        except (AttributeError, OSError, ValueError):
            return self  # no file descriptor (an embedded stream): no keys
        if os.isatty(self._fd):
            with contextlib.suppress(termios.error):
                self._saved = termios.tcgetattr(self._fd)
                tty.setcbreak(self._fd)
        self._thread = threading.Thread(target=self._read, name="openral-keys", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)
        if self._saved is not None:
            with contextlib.suppress(termios.error):
                termios.tcsetattr(self._fd, termios.TCSADRAIN, self._saved)

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._fd], [], [], 0.1)
                if not ready:
                    continue
                data = os.read(self._fd, 64)
            except OSError:
                return
            if not data:
                return  # end of input: no more keys
            for command in parse_keys(data, self._extra):
                self._on_command(command)
