"""What both console scripts share: one-line user errors with exit status 2, SIGTERM handled like Ctrl-C,
and ``--version``."""

from __future__ import annotations

import signal
import sys
import threading

import typer

from rangemcl.errors import InputError


def run_app(app: typer.Typer, prog: str) -> None:
    """Run a typer app; an :class:`InputError` becomes one line on stderr and exit status 2, and so does a
    command line that does not parse (an unknown command or option, a missing or mistyped value), with a
    pointer to the command's ``--help``.

    SIGTERM (``kill``, a batch system's time limit) raises ``KeyboardInterrupt`` as Ctrl-C does, so that
    commands keep what they computed and remove their temporary files instead of dying on the spot."""
    exceptions = _click_exceptions()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
    try:
        code = app(prog_name=prog, standalone_mode=False)
    except InputError as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        sys.exit(2)
    except exceptions.ClickException as err:
        if type(err).__name__ == "NoArgsIsHelpError":  # the bare program: its help, as typer shows it
            from typer import rich_utils

            rich_utils.rich_format_error(err)
            sys.exit(err.exit_code)
        if not isinstance(err, exceptions.UsageError):
            err.show()
            sys.exit(err.exit_code)
        message = " ".join(err.format_message().split())
        where = err.ctx.command_path if err.ctx is not None else prog
        print(f"{prog}: error: {message} (see '{where} --help')", file=sys.stderr)
        sys.exit(2)
    except typer.Abort:
        print("Aborted!", file=sys.stderr)
        sys.exit(1)
    sys.exit(code if isinstance(code, int) else 0)


def _click_exceptions():
    """The exceptions module of the click that typer runs on (recent typer versions carry their own)."""
    try:
        from typer._click import exceptions
    except ImportError:
        from click import exceptions
    return exceptions


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


def version_option(version: str):
    """A ``--version`` option that prints ``version`` and exits."""

    def show(value: bool) -> None:
        if value:
            typer.echo(version)
            raise typer.Exit()

    return typer.Option(False, "--version", help="Print the version and exit.", callback=show, is_eager=True)
