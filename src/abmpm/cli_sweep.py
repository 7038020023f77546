"""``abmpm sweep``: a scene run for every combination of values (a wedge)."""

from __future__ import annotations

import sys
from pathlib import Path

from rich.table import Table

from abmpm.arguments import frames_arg as _frames_arg
from abmpm.arguments import threads_arg as _threads_arg
from abmpm.cli_common import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_OK
from abmpm.cli_common import esc as _esc
from abmpm.cli_common import stderr_console as _stderr
from abmpm.cli_common import stdout_console as _stdout
from abmpm.sweep import feasible_on, import_ray, parse_set, plan_sweep, run_sweep

__all__ = ["add_parsers"]


def _cmd_sweep(args) -> int:
    if args.ray:
        import_ray()  # "--ray needs ray" before anything else
    values = parse_set(args.set)
    # every combination is validated (and, run here, checked to fit) before any run
    plan = plan_sweep(args.scene, values, check=None if args.ray else feasible_on(args.device))
    name = plan.source.data.get("name") or plan.source.default_name or "scene"
    out = Path(args.out) if args.out else Path("out") / f"{name}_sweep"
    con = _stderr()
    n = len(plan.runs)
    if not args.quiet:
        where = f"on Ray ({args.ray})" if args.ray else "one after another"
        con.print(f"[bold]abmpm[/bold] sweep [cyan]{_esc(args.scene)}[/cyan]: {n} run{'s' * (n != 1)} "
                  f"{where} -> {_esc(out)}")

    def on_start(i, n, run_name):
        if not args.quiet:
            con.print(f"[{i}/{n}] {'queued' if args.ray else 'running'} {run_name}", markup=False)

    def on_done(i, n, row):
        if args.quiet:
            return
        status = row.get("status")
        color = "green" if status == "completed" else "red"
        figures = ""
        if row.get("particle_count") is not None:
            figures = f", {row['particle_count']:,} particles, {row.get('steps', 0):,} steps"
            if row.get("wall_seconds") is not None:
                figures += f" in {row['wall_seconds']:.1f} s"
        msg = f" ({_esc(row['message'])})" if row.get("message") and status != "completed" else ""
        con.print(f"{_esc(f'[{i}/{n}]')} {_esc(row['run'])}: [{color}]{_esc(status)}[/{color}]{figures}{msg}")

    try:
        rows = run_sweep(
            args.scene, values, out, frames=args.frames, device=args.device, threads=args.threads,
            preview=not args.no_preview, ray=args.ray, on_start=on_start, on_done=on_done, plan=plan,
        )
    except KeyboardInterrupt:
        print(f"interrupted; the finished runs are in {out / 'sweep.csv'}", file=sys.stderr)
        return EXIT_INTERRUPTED
    failed = [r for r in rows if r.get("status") != "completed"]
    if not args.quiet:
        _print_sweep_table(rows, out)
    if failed:
        kinds = ", ".join(f"{sum(r.get('status') == k for r in failed)} {k}"
                          for k in dict.fromkeys(r.get("status") for r in failed))
        print(f"error: {len(failed)} of {len(rows)} runs failed ({kinds}); see {out / 'sweep.csv'}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def _print_sweep_table(rows: list[dict], out: Path) -> None:
    def num(v, fmt):
        return "" if v is None else format(v, fmt)

    failed = any(r.get("status") != "completed" for r in rows)
    table = Table(title=f"sweep: {len(rows)} runs")
    table.add_column("run", style="cyan", no_wrap=True)
    table.add_column("status", no_wrap=True)
    for head in ("particles", "steps", "steps/s", "wall s"):
        table.add_column(head, justify="right", no_wrap=True)
    if failed:
        table.add_column("message")
    for r in rows:
        status = r.get("status") or "?"
        color = "green" if status == "completed" else "red"
        cells = [
            _esc(r.get("run")), f"[{color}]{_esc(status)}[/{color}]",
            num(r.get("particle_count"), ","), num(r.get("steps"), ","),
            num(r.get("steps_per_second"), ",.0f"), num(r.get("wall_seconds"), ".1f"),
        ]
        if failed:
            cells.append(_esc(r.get("message") or "") if status != "completed" else "")
        table.add_row(*cells)
    con = _stdout()
    con.print(table)
    con.print(f"results: {_esc(out / 'sweep.csv')}, {_esc(out / 'sweep.json')}")


def add_parsers(sub) -> None:
    """Add ``sweep`` to the subparsers ``sub`` of ``abmpm``."""
    w = sub.add_parser("sweep", help="run a scene for every combination of values (a wedge)",
                       description="Run SCENE once per combination of the --set values (their Cartesian "
                                   "product), each into DIR/<key=value,...>/, and write DIR/sweep.csv and "
                                   "DIR/sweep.json. Exit status 2 if any run failed.")
    w.add_argument("scene", metavar="SCENE", help="scene file (.toml) or built-in name (see `abmpm scenes`)")
    w.add_argument("--set", "-s", dest="set", action="append", required=True, metavar="KEY=V1,V2,...",
                   help="a scene key and its values, e.g. simulation.dx=0.02,0.01 or materials[0].viscosity=0,1e-3 "
                        "(TOML values; bare words are strings); repeat for more keys")
    w.add_argument("--out", "-o", metavar="DIR", help="sweep folder (default: out/<scene name>_sweep/)")
    w.add_argument("--frames", "-n", type=_frames_arg, metavar="N", help="frames per run (default: duration * fps)")
    w.add_argument("--device", "-d", metavar="DEVICE",
                   help="cpu, cuda or cuda:N (default: the scene's, else cuda when available)")
    w.add_argument("--threads", "-j", type=_threads_arg, metavar="N",
                   help="CPU threads per run (default: 1 on Ray, else $ABMPM_THREADS or every core)")
    w.add_argument("--ray", metavar="auto|local|ADDRESS",
                   help="run as Ray tasks: auto (the running cluster, else a new local one), local (a new "
                        "local one) or a cluster address; needs pip install 'abmpm[sweep]'")
    w.add_argument("--no-preview", action="store_true", help="no preview.mp4 / preview.png per run")
    w.add_argument("--quiet", "-q", action="store_true", help="no progress lines or table")
    w.set_defaults(func=_cmd_sweep)
