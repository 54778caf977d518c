"""Real cameras through LeRobot's camera classes.

``spec``: ``--camera NAME=SPEC`` and rig ``[cameras.NAME]`` tables -> LeRobot camera configs;
``real``: :class:`~beavr_sim.cameras.real.RealCameras`, owning the LeRobot cameras and handing
the recorder their newest frames with capture ages; ``errors``: their one-line errors.
Submodules are imported where used (LeRobot is a heavy import).
"""
