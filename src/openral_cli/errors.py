"""The one place errors become exit codes: 2 for configuration, 1 for run-time failures."""

from __future__ import annotations

import sys
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import click

from openral_core import ROSConfigError, ROSError

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_CONFIG = 2
EXIT_SIGINT = 130
EXIT_SIGTERM = 143


@contextmanager
def exit_codes(debug: bool, echo: Callable[[str], None] | None = None) -> Iterator[None]:
    """Turn ``ROSError`` into a one-line message and an exit code; tracebacks only with ``debug``."""
    say = echo or (lambda text: click.echo(text, err=True))
    try:
        yield
    except ROSConfigError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        say(f"error: {exc}")
        raise SystemExit(EXIT_CONFIG) from None
    except ROSError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        say(f"error: {type(exc).__name__}: {exc}")
        raise SystemExit(EXIT_RUNTIME) from None
