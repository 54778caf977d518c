"""Benchmarks (``python -m beavr_sim.bench <name>``): speed targets are checked here, not in tests."""
