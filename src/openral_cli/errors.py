"""The one place errors become exit codes: 2 for configuration, 1 for run-time failures."""

from __future__ import annotations

import sys
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import click

from openral_core import ROSConfigError, ROSError
from openral_core.errors import one_line

EXIT_OK = 0
EXIT_RUNTIME = 1
EXIT_CONFIG = 2
EXIT_SIGINT = 130
EXIT_SIGTERM = 143


@contextmanager
def exit_codes(debug: bool, echo: Callable[[str], None] | None = None) -> Iterator[None]:
    """Turn errors into one line on stderr and an exit code; tracebacks only with ``debug``.

    ``ROSConfigError`` exits 2, and so does an error caused by one (a skill's ``configure`` that
    found its parameters wrong); any other ``ROSError`` 1. Anything else is a defect in openral or
    a plugin: it is reported on one line too (exit 1), with the traceback under ``--debug``.
    """
    say = echo or (lambda text: click.echo(text, err=True))
    try:
        yield
    except ROSConfigError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        say(f"error: {one_line(str(exc))}")
        raise SystemExit(EXIT_CONFIG) from None
    except ROSError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        if isinstance(exc.__cause__, ROSConfigError):  # a skill's configure found its configuration wrong
            say(f"error: {one_line(str(exc.__cause__))}")
            raise SystemExit(EXIT_CONFIG) from None
        say(f"error: {type(exc).__name__}: {one_line(str(exc))}")
        raise SystemExit(EXIT_RUNTIME) from None
    except Exception as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        say(f"error: unexpected {type(exc).__name__}: {one_line(str(exc))} (run with --debug for the traceback)")
        raise SystemExit(EXIT_RUNTIME) from None
