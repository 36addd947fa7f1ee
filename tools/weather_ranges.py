#!/usr/bin/env python3
"""How far each preset sees a face-on 10 % and 80 % target in clear air, fog and rain, by the realistic
sensor model (``simbed/sim/returns.py``, ``simbed/sim/weather.py``): the range at which the target's signal
meets the detection threshold (detected with the datasheet's probability, 90 %). Prints a Markdown table.

    python tools/weather_ranges.py      # clear, fog:1000, fog:200, fog:50, rain:10, rain:50
    python tools/weather_ranges.py --weather fog:100 rain:25
"""

from __future__ import annotations

import argparse

from rangemcl.sensors import load_spec
from simbed.sim.returns import ReturnModel
from simbed.sim.weather import Weather

PRESETS = ("mq-8", "vlp-16", "hdl-32e", "hdl-64e", "os1-64", "os1-128")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--weather", nargs="+", default=["clear", "fog:1000", "fog:200", "fog:50", "rain:10", "rain:50"]
    )
    args = ap.parse_args()
    skies = [Weather.parse(w) for w in args.weather]
    print("| preset | " + " | ".join(f"{w} (10 % / 80 %, m)" for w in skies) + " |")
    print("|---|" + "---|" * len(skies))
    for name in PRESETS:
        spec = load_spec(name)
        cells = []
        for sky in skies:
            m = ReturnModel.for_spec(spec, sky)
            r10, r80 = (min(m.range_limit_m(rho), spec.max_range_m) for rho in (0.1, 0.8))
            cells.append(f"{r10:.0f} / {r80:.0f}")
        print(f"| `{name}` | " + " | ".join(cells) + " |")
    print(
        "\nCapped at each preset's maximum range. Extinction per metre: "
        + ", ".join(f"{s}: {s.extinction_per_m:.4f}" for s in skies)
    )


if __name__ == "__main__":
    main()
