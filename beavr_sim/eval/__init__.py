"""Policy evaluation in the gym envs: LeRobot policies (ACT, Diffusion, SmolVLA, ...) loaded
through LeRobot's own factory, run synchronously or in BEAVR's think-act loop."""
