"""MimicGen-style augmentation: a few recorded demonstrations -> many, on the twin.

``python -m beavr_sim.datasets augment --source SRC --episodes N --seed S --out OUT``: each
source episode is replayed on the twin from its seed (:mod:`.replay`), split into
object-centric segments from contacts and object motion (:mod:`.segments`), and carried into
new scenes (the task's reset at new seeds): each segment's palm trajectory moves with its
reference object, segments are bridged by interpolated moves (:mod:`.frames`), the arm follows
through the operator's IK and the twin's guard, the fingers replay the source's, and the task's
checker keeps the successes (:mod:`.episode`). Two arms: :mod:`.coordination` (DexMimicGen's
constraints) and :mod:`.mirror` (a source episode's left/right mirror image). A source that
lost its episode log: :mod:`.recover`, :mod:`.replay_match`. The run itself (seeds, workers,
resume, merge) is :func:`beavr_sim.synthetic.generate.generate`'s, with a source in place of
the expert.
"""
