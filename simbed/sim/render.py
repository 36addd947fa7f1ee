"""Pictures of a scene: MuJoCo offscreen rendering (headless through EGL) to PNG."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write
from rangemcl.errors import InputError


def render_png(
    world, out: str | os.PathLike, *, camera: str | None = None, width: int = 1280, height: int = 960
):
    """Render the world's current state to a PNG (see :func:`render_rgb`)."""
    from PIL import Image

    image = render_rgb(world, camera=camera, width=width, height=height)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, lambda fh: Image.fromarray(image).save(fh, format="PNG"))
    return out


def render_rgb(world, *, camera: str | None = None, width: int = 640, height: int = 480) -> np.ndarray:
    """The world's current state as an ``(height, width, 3)`` uint8 image. Without ``camera``, a view from
    above and behind the car (or an overview when there is no car)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    import mujoco

    model, data = world.model, world.data
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    try:
        renderer = mujoco.Renderer(model, height, width)
    except Exception as err:
        raise InputError(f"cannot render offscreen ({err}); set MUJOCO_GL=egl or osmesa") from None
    mujoco.mj_forward(model, data)
    if camera is not None:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            raise InputError(f"{world.path}: no camera named {camera!r}")
        renderer.update_scene(data, camera=camera)
    else:
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        if world.car is not None:
            T = world.car.pose(data)
            cam.lookat[:] = T[:3, 3] + T[:3, 0] * 8.0
            cam.azimuth = float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))
            cam.elevation, cam.distance = -25.0, 35.0
        else:
            cam.lookat[:] = model.stat.center
            cam.elevation, cam.distance = -60.0, 1.5 * model.stat.extent
        renderer.update_scene(data, camera=cam)
    image = np.asarray(renderer.render()).copy()
    renderer.close()
    return image
