"""Stage 1, the detector: hand tracking in, validated :class:`~beavr_sim.wire.hand.HandFrame` out.

The BEAVR Quest app's protocol (:mod:`.quest_protocol`) and sockets (:mod:`.quest_io`), other
trackers' joint layouts (:mod:`.layouts`), the sources the runners poll (:mod:`.sources`: Quest,
recorded trace, in-memory) and the stream checks (:mod:`.validation`).
"""
