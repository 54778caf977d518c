"""LeRobot plugin: beavr_sim's benchmark tasks as a LeRobot env (--env.type=beavr_sim).

Imported by LeRobot's ``register_third_party_plugins``; importing it registers the config.
"""

from beavr_sim.integrations.env import ENV_TYPE, BeavrSimEnvConfig

__all__ = ["ENV_TYPE", "BeavrSimEnvConfig"]
