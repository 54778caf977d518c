"""Real cameras through LeRobot's camera classes, and where they stand.

``spec``: ``--camera NAME=SPEC`` and rig ``[cameras.NAME]`` tables -> LeRobot camera configs;
``real``: :class:`~beavr_sim.cameras.real.RealCameras`, owning the LeRobot cameras and handing
the recorder their newest frames with capture ages; ``poses``: the twin cameras a rig table's
``T_world_camera`` places; ``calibrate``: that pose from images of a ChArUco board
(``python -m beavr_sim.cameras calibrate``); ``names``: a twin camera beside a real one of
its name is recorded as ``NAME_twin``; ``errors``: their one-line errors.
Submodules are imported where used (LeRobot is a heavy import).
"""
