"""Stage 3, the twin: joint commands in, the simulated robot moves, robot state out.

:mod:`.twin` (:class:`~beavr_sim.twin.twin.TwinInterface`) owns the env and composes the
commands into actions; :mod:`.guard` (:class:`~beavr_sim.twin.guard.CollisionGuard`) refuses a
command that would collide. The hardware mirror (``beavr_sim.hardware``) sits beside it and
sends only what the guard let through.
"""
