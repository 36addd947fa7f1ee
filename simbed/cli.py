"""The ``simbed`` console script. Scenes, drives and recordings arrive with the test-bed issue."""

from __future__ import annotations

import typer

from rangemcl.cliutil import run_app, version_option
from simbed import __version__

app = typer.Typer(
    name="simbed",
    help="Simulation test bed: MuJoCo towns, a driven car, simulated LiDAR, recorded drives.",
    add_completion=False,
    pretty_exceptions_enable=False,
    invoke_without_command=True,
)


@app.callback()
def _root(ctx: typer.Context, version: bool = version_option(__version__)) -> None:
    """Simulation test bed: MuJoCo towns, a driven car, simulated LiDAR, recorded drives."""
    if ctx.invoked_subcommand is None:
        typer.echo(ctx.get_help())


def main() -> None:
    run_app(app, "simbed")


if __name__ == "__main__":
    main()
