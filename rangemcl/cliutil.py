"""What both console scripts share: one-line user errors with exit status 2, and ``--version``."""

from __future__ import annotations

import sys

import typer

from rangemcl.errors import InputError


def run_app(app: typer.Typer, prog: str) -> None:
    """Run a typer app; an :class:`InputError` becomes one line on stderr and exit status 2."""
    try:
        app(prog_name=prog)
    except InputError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        sys.exit(2)


def version_option(version: str):
    """A ``--version`` option that prints ``version`` and exits."""

    def show(value: bool) -> None:
        if value:
            typer.echo(version)
            raise typer.Exit()

    return typer.Option(False, "--version", help="Print the version and exit.", callback=show, is_eager=True)
