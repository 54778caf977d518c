"""Stage 2, the operator: hand frames in, one :class:`~beavr_sim.wire.records.JointCommand` per
effector out.

:mod:`.operator` owns the per-effector state (side is data); the mathematics is one module per
concept: the palm frame (:mod:`.palm`), filters, the arm's relative motion mapping and IK, the
LEAP finger retargeting, their collision rows and Jacobians, the per-tick QP
(:mod:`.qp`), and the compiled arithmetic all of these share (:mod:`.kernels`).
"""
