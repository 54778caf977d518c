"""``python -m beavr_sim.bench policies``: the policy table (ACT, Diffusion, the scripted
expert through the teleop pipeline) on fixed seeds, every stage cached by its configuration.

Modules: ``config`` (what a run is: frozen stage configs, seeds, presets, cache keys),
``train`` (``lerobot-train`` as a subprocess, resumable), ``stages`` (the cached stages and
the pipeline), ``table`` (markdown and JSON), ``cli`` (the command line).
"""
