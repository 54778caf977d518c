"""LeRobot plugin: beavr_sim's xArm7 + LEAP rigs and RX-1 as a LeRobot robot (--robot.type=beavr_sim).

Imported by LeRobot's ``register_third_party_plugins``; importing it registers the config.
"""

from beavr_sim.integrations.config_robot import ROBOT_TYPE, BeavrSimRobotConfig
from beavr_sim.integrations.robot import BeavrSimRobot

__all__ = ["ROBOT_TYPE", "BeavrSimRobot", "BeavrSimRobotConfig"]
