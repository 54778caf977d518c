"""The xArm7: its config (joint limits, safety set), driver (UFACTORY's SDK) and emulator."""
