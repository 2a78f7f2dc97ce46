"""Simulators that make test and demo material: antique-looking stereo cards from photographs with
known geometry (:mod:`simulation.cards`). Not part of the pure pipeline: the pipeline never
imports them; the demo, the tests and the benchmarks do."""
