"""simbed: the MuJoCo + Warp simulation test bed for LiDAR localization (uses rangemcl's ray casting).

Importing it registers the gymnasium environments ``simbed/LocalizationTrial-v0`` and ``simbed/Drive-v0``
(string entry points: nothing heavy is imported until one is made); see :mod:`simbed.trials.envs`.
"""

import os

from rangemcl import __version__ as __version__  # one version for both packages (one distribution)

# MuJoCo picks its OpenGL backend when it is first imported: headless machines need EGL for pictures.
if not os.environ.get("DISPLAY"):
    os.environ.setdefault("MUJOCO_GL", "egl")


def _register_envs() -> None:
    try:
        from gymnasium.envs.registration import register, registry
    except ImportError:  # pragma: no cover - gymnasium is a dependency; tolerate its absence at import
        return
    if "simbed/LocalizationTrial-v0" not in registry:
        register(
            id="simbed/LocalizationTrial-v0",
            entry_point="simbed.trials.envs:LocalizationTrialEnv",
            max_episode_steps=3000,
        )
    if "simbed/Drive-v0" not in registry:
        register(id="simbed/Drive-v0", entry_point="simbed.trials.envs:DriveEnv", max_episode_steps=1000)


_register_envs()
