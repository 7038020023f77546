"""The level-interface matrix's report (``abmpm bench --suite interface``): one line per
case of ``bench/interface.py``, the plate cases' tally against issue 26's goals, and the
seeds' standard error."""

from __future__ import annotations

import numpy as np


def summary_line(key: str, r: dict) -> str:
    """One line of the suite's report for a case of ``run_interface_suite``."""
    steps = f"steps {r['steps_ratio']}x finest's" if "steps_ratio" in r else ""
    if key == "tank at rest":
        o, a, f = r["original"], r["adaptive"], r["finest"]
        return (f"level-1 J spread {r['J_spread_ratio']}x finest's, at the interface {r['interface_J_ratio']}x, "
                f"fastest particle {r['fastest_ratio']}x finest's (over the run {r['fastest_over_run_ratio']}x), "
                f"{steps}; J at the interface against the same depth far from it {a['depth_J_gap']:.4f} (goal 0.01; "
                f"finest {f['depth_J_gap']:.4f}), surface range across the interface "
                f"{a['interface_surface_range']:.4f} m (goal half a fine cell, {r['half_fine_cell']:.4f}; finest "
                f"{f['interface_surface_range']:.4f}), over the tank {a['surface_range']:.4f} m (finest "
                f"{f['surface_range']:.4f}, original {o['surface_range']:.4f})")
    if key == "jelly pressed through":
        return (f"mass through adaptive {r['adaptive']['through']:.4f}, finest {r['finest']['through']:.4f}, original "
                f"{r['original']['through']:.4f} -> adaptive / finest {r['through_ratio']} (goal 0.9-1.1); {steps}")
    if key == "layered tank at rest":
        return (f"level-1 J spread {r['J_spread_ratio']}x finest's at the same heights, fastest particle "
                f"{r['fastest_ratio']}x finest's, {steps}")
    if key == "blade cut":
        o, a, f = (1e3 * r[m]["width"] for m in ("original", "adaptive", "finest"))
        return (f"cut width original {o:.1f}, adaptive {a:.1f}, finest {f:.1f} mm -> adaptive / finest "
                f"{r['width_ratio']} (goal 0.9-1.1), roughness {r['roughness_ratio']}x finest's; {steps}")
    if key == "dam break":
        o, f = r["original"], r["finest"]
        return (f"the front's time across the box adaptive / finest {r['crossing_ratio']}, run-up at the wall "
                f"{r['runup_ratio']} (goal 0.9-1.1; original {o['crossing']:.3f} s, {o['runup']:.3f} m; finest "
                f"{f['crossing']:.3f} s, {f['runup']:.3f} m); {steps} (goal <= 1.05)")
    return (f"largest total momentum / one half's (0 exactly; finest's is float round-off) {r['drift']}; "
            f"kinetic energy at 0.4 s adaptive / finest {r['ke_ratio']}")


def plate_tally(rows: list[dict]) -> dict:
    """The plate cases against issue 26's goals: mass through within 10% of finest's, steps at
    most 1.05x finest's, and the mean (signed and absolute) log ratio of the mass through."""
    logs = [float(np.log(r["through_ratio"])) for r in rows if r["through_ratio"]]
    return {"cases": len(rows), "within_10pct": int(sum(abs(np.exp(x) - 1.0) <= 0.1 for x in logs)),
            "steps_within_5pct": int(sum(r["steps_ratio"] is not None and r["steps_ratio"] <= 1.05 for r in rows)),
            "mean_log_ratio": round(float(np.mean(logs)), 4) if logs else None,
            "mean_abs_log_ratio": round(float(np.mean(np.abs(logs))), 4) if logs else None}


def seed_error(r: dict) -> str:
    """"; standard error" and each mode's standard error of its mean mass through over its
    seeds, relative to the mean; "" for a case run on one seed."""
    parts = []
    for m in ("adaptive", "finest"):
        seeds = r[m]["through_seeds"]
        if len(seeds) > 1 and r[m]["through"]:
            parts.append(f"{m} {np.std(seeds, ddof=1) / np.sqrt(len(seeds)) / r[m]['through']:.1%}")
    return "; standard error " + ", ".join(parts) if parts else ""
