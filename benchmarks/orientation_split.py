"""The cards the orientation step was tuned on; the orientation benchmarks hold out every other card."""

from __future__ import annotations

# Tuned on these; every other card is held out (chosen before any measurement: alternate kinds).
TUNE = {
    "nypl_stereogranimator_demo1",
    "nypl_stereogranimator_demo3",
    "nypl_stereogranimator_demo5",
    "nypl_000206_pima_indians_of_arizona",
    "nypl_f0bf5ba0_ostrich_farm_columbian_exposition_front",
    "09995",
    "8618s",
}
