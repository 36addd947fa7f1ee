"""What both console scripts share: one-line user errors with exit status 2, SIGTERM handled like Ctrl-C,
and ``--version``."""

from __future__ import annotations

import signal
import sys
import threading

import typer

from rangemcl.errors import InputError


def run_app(app: typer.Typer, prog: str) -> None:
    """Run a typer app; an :class:`InputError` becomes one line on stderr and exit status 2.

    SIGTERM (``kill``, a batch system's time limit) raises ``KeyboardInterrupt`` as Ctrl-C does, so that
    commands keep what they computed and remove their temporary files instead of dying on the spot."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
    try:
        app(prog_name=prog)
    except InputError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        sys.exit(2)


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


def version_option(version: str):
    """A ``--version`` option that prints ``version`` and exits."""

    def show(value: bool) -> None:
        if value:
            typer.echo(version)
            raise typer.Exit()

    return typer.Option(False, "--version", help="Print the version and exit.", callback=show, is_eager=True)
