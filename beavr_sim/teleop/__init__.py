"""The runners: one process (:mod:`.pipeline`) or three (:mod:`.processes`), assembled from the
command line (:mod:`.session`, ``python -m beavr_sim.teleop``), with episode control and the
browser view's glue. The stages they run live in ``headset``, ``operator``, ``twin`` and ``wire``.
"""
