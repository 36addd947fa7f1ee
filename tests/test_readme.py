"""The Python example of README.md runs as written (so that README.md stays true)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    scope: dict = {}
    exec(compile(blocks[0], str(README), "exec"), scope)
    hits = scope["hits"]
    assert np.isfinite(hits.ranges[0]) and hits.mesh_ids[0] == scope["car"]  # the car stands in front
    assert np.isinf(hits.ranges[1]) and hits.mesh_ids[1] == -1  # the sky
    assert scope["ranges"].shape == (64, 1024)
    est = scope["info"].estimate  # the localizer found the pose the scan was taken from
    assert abs(est[0]) < 0.3 and abs(est[1] - 25.0) < 0.3 and abs(est[2]) < 0.02
