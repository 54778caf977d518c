"""The LEAP hand: its config (units, control table), driver (dynamixel_sdk) and emulator."""
