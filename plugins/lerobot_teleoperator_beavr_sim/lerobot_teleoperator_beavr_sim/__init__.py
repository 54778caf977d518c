"""LeRobot plugin: beavr_sim's Quest hand-tracking pipeline as a LeRobot teleoperator (--teleop.type=beavr_quest).

Imported by LeRobot's ``register_third_party_plugins``; importing it registers the config.
"""

from beavr_sim.integrations.config_teleoperator import TELEOP_TYPE, BeavrQuestTeleopConfig
from beavr_sim.integrations.teleoperator import BeavrQuestTeleop

__all__ = ["TELEOP_TYPE", "BeavrQuestTeleop", "BeavrQuestTeleopConfig"]
