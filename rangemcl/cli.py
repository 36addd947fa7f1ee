"""The ``rangemcl`` console script. Heavy imports live inside the commands so ``--help`` stays fast."""

from __future__ import annotations

from pathlib import Path

import typer

from rangemcl import __version__
from rangemcl.cliutil import run_app, version_option

app = typer.Typer(
    name="rangemcl",
    help="Range-image Monte Carlo LiDAR localization in triangle-mesh maps.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(version: bool = version_option(__version__)) -> None:
    """Range-image Monte Carlo LiDAR localization in triangle-mesh maps."""


@app.command()
def sensors(
    name: str = typer.Argument(None, help="A preset name or a sensor YAML file; omit to list the presets."),
) -> None:
    """List the LiDAR presets as a table, or print one sensor spec in full (as YAML)."""
    import sys

    import yaml
    from rich.console import Console
    from rich.table import Table

    from rangemcl.sensors import load_spec, preset_names

    console = Console(width=None if sys.stdout.isatty() else 160)  # pipes and logs get whole lines
    if name:
        spec = load_spec(name)
        console.print(f"# {spec.description}", markup=False)
        console.print(yaml.safe_dump(spec.to_dict(), sort_keys=False, width=100), markup=False)
        return
    table = Table(title="LiDAR presets (rangemcl sensors NAME for the full spec)")
    for col, justify in [
        ("name", "left"),
        ("beams", "right"),
        ("vertical FOV (deg)", "right"),
        ("columns", "right"),
        ("Hz", "right"),
        ("range (m)", "right"),
        ("noise (m)", "right"),
        ("description", "left"),
    ]:
        table.add_column(col, justify=justify, no_wrap=col != "description")
    for preset in preset_names():
        s = load_spec(preset)
        table.add_row(
            s.name,
            str(s.beams),
            f"{s.fov_down_deg:+.2f} .. {s.fov_up_deg:+.2f}",
            str(s.columns),
            f"{s.rotation_hz:g}",
            f"{s.min_range_m:g} .. {s.max_range_m:g}",
            f"{s.range_noise_m:g}",
            s.description,
        )
    console.print(table)


@app.command()
def sweep(
    sensor: str = typer.Option("os1-64", help="Preset name or sensor YAML file."),
    out: Path = typer.Option(Path("out/sweep"), help="Folder for the range image PNG and the scan .bin."),
    seed: int = typer.Option(0, help="Seed of the town layout and of the range noise."),
    device: str = typer.Option("cpu", help="Warp device: cpu or cuda."),
    threads: int = typer.Option(0, help="CPU threads (0 = all cores)."),
) -> None:
    """Cast one LiDAR sweep in a synthetic town through the Warp core and write what it saw."""
    import time

    import numpy as np

    from rangemcl import meshgen
    from rangemcl.plots import save_range_image_png
    from rangemcl.rangeimage import RangeImageGeometry
    from rangemcl.raycast import RayCaster
    from rangemcl.scanio import write_scan_bin
    from rangemcl.sensors import load_spec

    spec = load_spec(sensor)
    rng = np.random.default_rng(seed)
    town = meshgen.town(seed=seed)
    vertices, faces = town.merged()
    caster = RayCaster(device=device, threads=threads or None)
    caster.add_mesh(vertices, faces, name="town")
    geometry = RangeImageGeometry.for_spec(spec)

    x, y = float(town.road_xy[1]), float(town.road_xy[1]) + 12.0  # on a road, near a junction
    T_world_base = np.eye(4)
    T_world_base[:3, 3] = (x, y, float(meshgen.town_ground_height(x, y)))
    T_world_sensor = T_world_base @ spec.T_base_sensor

    t0 = time.perf_counter()
    ranges = caster.render(geometry, T_world_sensor, spec.max_range_m)
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    caster.render(geometry, T_world_sensor, spec.max_range_m)  # again, warm
    seconds = time.perf_counter() - t0
    valid = ranges >= spec.min_range_m
    noisy = ranges + rng.normal(0.0, spec.range_noise_m, ranges.shape).astype(np.float32)
    noisy = np.where(valid, noisy, 0.0).astype(np.float32)
    points = geometry.back_project(noisy)[valid]  # (N, 3) sensor frame

    out.mkdir(parents=True, exist_ok=True)
    png = save_range_image_png(out / f"range_{spec.name}.png", noisy, spec.max_range_m)
    scan = write_scan_bin(out / f"scan_{spec.name}.bin", points)
    n_rays = ranges.size
    typer.echo(
        f"{spec.name}: {spec.beams} x {spec.columns} rays in a town of {len(faces):,} triangles "
        f"({len(town.parts)} parts) on {device} with {caster.threads} thread(s)"
    )
    typer.echo(
        f"  {valid.sum():,} returns ({valid.mean():.1%}), median range {np.median(ranges[valid]):.1f} m, "
        f"cast in {seconds * 1e3:.0f} ms warm ({n_rays / seconds / 1e6:.2f} M rays/s; "
        f"first call {first_s * 1e3:.0f} ms)"
    )
    typer.echo(f"  wrote {png} and {scan}")


def main() -> None:
    run_app(app, "rangemcl")


if __name__ == "__main__":
    main()
