"""``python -m beavr_sim.bench policies``: the policy table (ACT, Diffusion, the scripted
expert through the teleop pipeline) on fixed seeds, every stage cached by its configuration.

Modules: ``config`` (what a run is: frozen stage configs, seeds, presets, cache keys),
``train`` (``lerobot-train`` as a subprocess, resumable and extendable, its loss curve),
``stages`` (the cached stages and the pipeline), ``table`` (markdown and JSON), ``plot`` (a
figure per task), ``cli`` (the command line).
"""
