"""Hardware drivers, their protocol emulators, and the rig that mirrors the twin."""
