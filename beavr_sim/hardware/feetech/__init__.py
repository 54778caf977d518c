"""The RX-1's Feetech servo groups: config (servo table, units), driver (scservo_sdk), emulator."""
