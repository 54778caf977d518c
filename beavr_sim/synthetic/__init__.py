"""Synthetic demonstrations: a task's scripted expert performed through the whole pipeline.

:mod:`.trace` turns an expert into the tracked human hands a VR operator would have produced
(``python -m beavr_sim.traces synth``); :mod:`.generate` replays such traces through the teleop
pipeline into a LeRobot dataset (``python -m beavr_sim.datasets generate``). It sits above the
runners it drives.
"""
