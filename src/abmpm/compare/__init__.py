"""Run one scene in several refinement modes and compare them (``abmpm compare``,
``abmpm paper``): particles, speed, the scene's outcome figures and leaks, written to
``DIR/table1.json`` and ``DIR/report.md`` with plots and a montage.

    from abmpm.compare import compare, run_paper
    records = compare("paper_cut", out="out/compare", frames=10)
"""

from __future__ import annotations

from abmpm.compare.core import MODES, apply_overrides, compare, measure, quick_scene, remeasure, run_paper
from abmpm.compare.paper import PAPER_CONTACT, PAPER_SCENES, PAPER_TABLE1, QUICK_OVERRIDES

__all__ = ["MODES", "PAPER_CONTACT", "PAPER_SCENES", "PAPER_TABLE1", "QUICK_OVERRIDES", "apply_overrides", "compare",
           "measure", "quick_scene", "remeasure", "run_paper"]
