"""The figures (outcome plot, montage) and ``report.md`` of a comparison."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np

from abmpm.compare.outcomes import PLOTTED, outcome_for
from abmpm.compare.paper import PAPER_GPU, PAPER_TABLE1
from abmpm.post.camera import Camera
from abmpm.post.preview import PREVIEW_SIZE, disk_frames, frame_image, region_lines

OUTCOME_PNG = "outcome.png"
MONTAGE_PNG = "montage.png"
MONTAGE_COLUMNS = 4
MODE_COLORS = {"original": "tab:blue", "adaptive": "tab:orange", "finest": "tab:green"}


def _plt():
    matplotlib.use("Agg")  # files only, never a window
    return plt


def plot_outcome(scene, records: list[dict], path: Path) -> Path | None:
    """The scene's outcome series against time, one line per mode (None: no series)."""
    key = PLOTTED.get(outcome_for(scene))
    lines = [(r["mode"], r["outcome"]["series"]) for r in records if key in r["outcome"].get("series", {})]
    if not key or not lines:
        return None
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for mode, s in lines:
        t = s.get("time") or s.get("ke_time") or list(range(len(s[key])))
        ax.plot(t[: len(s[key])], s[key], label=mode, color=MODE_COLORS.get(mode))
    ax.set_xlabel("time (s)")
    ax.set_ylabel(key.replace("_", " ") + (" (J)" if key == "kinetic_energy" else " (fraction of mass)"))
    ax.set_title(f"{scene.name}: {key.replace('_', ' ')}")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_montage(scene, records: list[dict], path: Path, columns: int = MONTAGE_COLUMNS) -> Path | None:
    """The modes (rows) at the same output frames (columns), drawn like the preview."""
    runs = [(r["mode"], Path(r["run_dir"])) for r in records]
    sources = {mode: dict(disk_frames(d)) for mode, d in runs}
    common = sorted(set.intersection(*(set(s) for s in sources.values()))) if sources else []
    if not common:
        return None
    picks = sorted({common[int(round(i))] for i in np.linspace(0, len(common) - 1, min(columns, len(common)))})
    st = scene.simulation
    camera = Camera.framing_box(st.domain_min, st.domain_max, *PREVIEW_SIZE)
    plt = _plt()
    fig, axes = plt.subplots(len(runs), len(picks), figsize=(3.2 * len(picks), 2.5 * len(runs)), squeeze=False)
    for i, (mode, d) in enumerate(runs):
        lines = region_lines(d)
        for j, n in enumerate(picks):
            ax = axes[i][j]
            ax.imshow(frame_image(scene, sources[mode][n](), camera, lines=lines))
            ax.set_xticks([])
            ax.set_yticks([])
            if j == 0:
                ax.set_ylabel(mode)
            if i == 0:
                ax.set_title(f"t = {n / st.fps:.2f} s", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def scene_figures(scene, records: list[dict], folder: Path) -> dict:
    """Write the outcome plot and the montage of one scene; returns their paths."""
    out = {}
    p = plot_outcome(scene, records, folder / OUTCOME_PNG)
    if p:
        out["outcome"] = p
    p = plot_montage(scene, records, folder / MONTAGE_PNG)
    if p:
        out["montage"] = p
    return out


def _num(v, fmt: str) -> str:
    return "–" if v is None else format(v, fmt)


def _finals(final: dict) -> str:
    parts = []
    for k, v in final.items():
        if isinstance(v, float):
            parts.append(f"{k} {v:.4g}")
        elif isinstance(v, list):
            parts.append(f"{k} [" + ", ".join(f"{x:.3g}" for x in v) + "]")
        else:
            parts.append(f"{k} {v if v is not None else '–'}")
    return "; ".join(parts) or "–"


def adaptive_against_finest(adaptive: dict, finest: dict) -> dict:
    """The method's pay-off from two records (or two ``window`` dicts) of one scene:
    ``score`` = (adaptive steps/s / finest steps/s) / (finest particles / adaptive
    particles), 1 when an adaptive particle-step costs what a finest one does;
    ``wall`` = adaptive / finest wall seconds per simulated second (a whole run's
    counts its frames written; a window's is simulation only). None where a figure is
    missing."""
    sa, sf = adaptive.get("steps_per_second"), finest.get("steps_per_second")
    pa, pf = adaptive.get("particles_mean"), finest.get("particles_mean")
    score = (sa / sf) * (pa / pf) if sa and sf and pa and pf else None
    wa, wf = adaptive.get("wall_seconds_per_sim_second"), finest.get("wall_seconds_per_sim_second")
    return {"score": score, "wall": wa / wf if wa and wf else None}


def paper_against_finest(name: str) -> dict:
    """The same figures from the paper's Table 1 (it gives steps/s, not wall time: with
    the same time step in both modes, finest steps/s / adaptive steps/s is the wall
    time ratio)."""
    row = PAPER_TABLE1[name]
    sa, sf = row["steps_per_second"]["adaptive"], row["steps_per_second"]["finest"]
    pa, pf = row["particles"]["adaptive"], row["particles"]["finest"]
    return {"score": (sa / sf) * (pa / pf), "wall": sf / sa}


def _goals_table(records: list[dict]) -> list[str]:
    """Score and wall-time ratio of adaptive against finest per scene, ours beside the
    paper's (issue goals: score >= 0.8, wall <= 0.5)."""
    rows = []
    for name in dict.fromkeys(r["scene"] for r in records):
        by_mode = {r["mode"]: r for r in records if r["scene"] == name}
        if "adaptive" not in by_mode or "finest" not in by_mode:
            continue
        whole = adaptive_against_finest(by_mode["adaptive"], by_mode["finest"])
        wa, wf = by_mode["adaptive"].get("window"), by_mode["finest"].get("window")
        after = adaptive_against_finest(wa, wf) if wa and wf else {"score": None, "wall": None}
        paper = paper_against_finest(name) if name in PAPER_TABLE1 else {"score": None, "wall": None}
        rows.append(f"| {name} | {_num(whole['score'], '.2f')} | {_num(whole['wall'], '.2f')} "
                    f"| {_num(after['score'], '.2f')} | {_num(after['wall'], '.2f')} "
                    f"| {_num(paper['score'], '.2f')} | {_num(paper['wall'], '.2f')} |")
    if not rows:
        return []
    return ["", "## Adaptive against finest", "",
            "score = (adaptive steps/s / finest steps/s) x (adaptive particles / finest particles): 1 when an "
            "adaptive particle-step costs what a finest one does. wall = adaptive / finest wall seconds per "
            "simulated second (the whole run with its output; after contact, simulation only). The paper's from its Table 1 (finest / adaptive steps/s as its wall ratio).", "",
            "| scene | score, whole run | wall, whole run | score, after contact | wall, after contact "
            "| paper's score | paper's wall |", "|---|---|---|---|---|---|---|", *rows]


def _window_table(records: list[dict]) -> list[str]:
    """The runs timed over a window after contact (``abmpm paper --window``)."""
    timed = [r for r in records if r.get("window")]
    if not timed:
        return []
    lines = ["", "## After contact", "",
             "Steps/s and particles over the window from the first output frame at or after the scene's contact "
             "(`abmpm.compare.PAPER_CONTACT`) to the end of the run.", "",
             "| scene | mode | window (s) | particles mean | particles end | paper particles | steps/s "
             "| paper steps/s | wall s per sim s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in timed:
        w = r["window"]
        paper = PAPER_TABLE1.get(r["scene"], {})
        lines.append(
            f"| {r['scene']} | {r['mode']} | {w['start']:.3f}-{w['end']:.3f} | {_num(w.get('particles_mean'), ',.0f')} "
            f"| {_num(w.get('particles_end'), ',')} | {_num(paper.get('particles', {}).get(r['mode']), ',')} "
            f"| {_num(w.get('steps_per_second'), '.2f')} | {_num(paper.get('steps_per_second', {}).get(r['mode']), '.1f')} "
            f"| {_num(w.get('wall_seconds_per_sim_second'), '.0f')} |")
    return lines


def render_report(out: Path, records: list[dict]) -> str:
    scenes = list(dict.fromkeys(r["scene"] for r in records))
    lines = ["# Mode comparison (after the paper's Table 1)", ""]
    devices = sorted({str(r.get("device")) for r in records})
    lines += [f"Runs on: {', '.join(devices)}. Paper: {PAPER_GPU}. Particles: ours mean / at the end; "
              "the paper's counts and steps/s are from its Table 1.", ""]
    lines += ["| scene | mode | dx | dx' | particles mean | particles end | paper particles | steps/s | "
              "paper steps/s | wall s per sim s | leaked | status |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        paper = PAPER_TABLE1.get(r["scene"], {})
        pp = paper.get("particles", {}).get(r["mode"])
        ps = paper.get("steps_per_second", {}).get(r["mode"])
        leaked = r.get("leaks", {}).get("total")
        label = r["scene"] + (" (quick)" if r.get("quick") else "")
        lines.append(
            f"| {label} | {r['mode']} | {r['dx']:.4g} | {r['dx_fine']:.4g} "
            f"| {_num(r.get('particles_mean'), ',.0f')} "
            f"| {_num(r.get('particles_end'), ',')} | {_num(pp, ',')} | {_num(r.get('steps_per_second'), '.1f')} "
            f"| {_num(ps, '.1f')} | {_num(r.get('wall_seconds_per_sim_second'), '.0f')} | {_num(leaked, 'd')} "
            f"| {r.get('status')} |"
        )
    lines += _window_table(records)
    lines += _goals_table(records)
    for name in scenes:
        recs = [r for r in records if r["scene"] == name]
        paper = PAPER_TABLE1.get(name)
        lines += ["", f"## {name}" + (f" ({paper['figure']})" if paper else ""), ""]
        lines += ["| mode | outcome | leaks |", "|---|---|---|"]
        for r in recs:
            lk = ", ".join(f"{k} {v}" for k, v in (r.get("leaks") or {}).items()) or "–"
            lines.append(f"| {r['mode']} | {_finals(r.get('outcome', {}).get('final', {}))} | {lk} |")
        for fig, title in ((OUTCOME_PNG, "outcome against time"), (MONTAGE_PNG, "the modes at matching times")):
            if (out / name / fig).exists():
                lines += ["", f"![{name}: {title}]({name}/{fig})"]
    lines += ["", "Leaks counted: particles not finite or more than half a coarse cell outside the domain in the last "
              "frame; for a letter "
              "panel, particles that crossed its plane between two output frames at a point of solid panel more "
              "than one coarse cell from a hole or edge; for an hourglass, particles of the last frame more than "
              "one coarse cell outside the glass that never were above its open mouth (`over_the_mouth`: "
              "splashed out over the rim, not counted).", ""]
    return "\n".join(lines)


def write_report(out: Path, records: list[dict]) -> Path:
    path = Path(out) / "report.md"
    path.write_text(render_report(Path(out), records))
    return path
