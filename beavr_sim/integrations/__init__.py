"""beavr_sim inside LeRobot's own commands: an env, a robot and a teleoperator plugin.

The plugin distributions in ``plugins/`` (``lerobot_env_beavr_sim``,
``lerobot_robot_beavr_sim``, ``lerobot_teleoperator_beavr_sim``) only import these modules;
LeRobot's ``register_third_party_plugins`` imports the plugins, and the config classes here
register themselves with LeRobot's choice registries on import:

- :mod:`~beavr_sim.integrations.env`: ``--env.type=beavr_sim`` (``lerobot-eval``,
  ``lerobot-train``'s periodic evaluation) over the ``beavr_sim/<Task>-v0`` gym envs;
- :mod:`~beavr_sim.integrations.config_robot` / :mod:`~beavr_sim.integrations.robot`:
  ``--robot.type=beavr_sim``: the twin (``hardware=sim``) or a rig mirrored through the twin's
  guard (``emulated`` or a rig file);
- :mod:`~beavr_sim.integrations.config_teleoperator` /
  :mod:`~beavr_sim.integrations.teleoperator`: ``--teleop.type=beavr_quest``: the Quest
  hand-tracking pipeline (detector + operator) fed by the headset or a VR trace.

Nothing here is imported by ``import beavr_sim``: LeRobot is imported only by these modules.
"""
