"""What crosses a stage boundary, and how it travels between processes.

In one process the stages hand each other plain records: :class:`~beavr_sim.wire.hand.HandFrame`
(headset -> operator), :class:`~beavr_sim.wire.records.JointCommand` (operator -> twin ->
hardware), :class:`~beavr_sim.wire.records.TwinState` and :class:`~beavr_sim.wire.records.Tick`
(runner -> recorder, views, logs). Between processes they travel as the typed msgpack messages of
:mod:`~beavr_sim.wire.messages` over :mod:`~beavr_sim.wire.transport` (the only pipeline ZMQ
code), on the ports of :mod:`~beavr_sim.wire.ports` (every port number). This package is the
lowest of the pipeline: it imports no other stage, so every stage can import it.
"""
