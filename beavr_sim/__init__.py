"""beavr_sim: a simulation-first digital twin for VR teleoperation of dexterous robots.

Importing the package registers the gymnasium environments (``beavr_sim/<Task>-v0``);
the registration is lazy, so nothing heavy is imported here.
"""

import os

# Headless machines render through EGL (Mesa); set before anything imports mujoco's GL layer.
if not os.environ.get("DISPLAY") and not os.environ.get("MUJOCO_GL"):
    os.environ["MUJOCO_GL"] = "egl"

from beavr_sim.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()

__all__ = ["__version__", "register_envs"]
