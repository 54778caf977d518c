"""LeRobot datasets from teleoperation: features, a crash-safe episode writer, the recorder that
turns teleop ticks into frames, and ``python -m beavr_sim.datasets generate``."""
