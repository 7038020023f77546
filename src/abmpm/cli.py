"""The ``abmpm`` command line.

    abmpm run SCENE [--out DIR] [--device cpu|cuda] [--frames N] [--resume] [--no-preview] [--view]
    abmpm scenes                 built-in scenes
    abmpm info                   versions and devices
    abmpm render DIR [--beauty]  re-render the preview of a finished run (--beauty: path-traced, Mitsuba)
    abmpm blender DIR            the run as an animated Blender scene (DIR/abmpm.blend)
    abmpm view DIR [--port N]    browse a run's frames in the web browser (viser)
    abmpm sweep SCENE --set KEY=V1,V2,...   a run per combination of values (a wedge)
    abmpm surface DIR            surface meshes of a finished run
    abmpm bench                  performance benchmark
    abmpm compare SCENE          the scene in original, adaptive and finest mode, with a report
    abmpm paper [--quick]        the paper's Table 1 experiments (compare for each)

User errors (a bad scene key, a missing mesh, an unwritable folder, a scene too big
for the machine, a blow-up) print one line ``error: <message>`` per problem on
stderr and exit with status 2; command-line mistakes print one line
``abmpm: error: <message>`` (no usage block) and exit with status 2. Paths and names
are printed literally (``[`` in a path is not rich markup).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import platform
import shlex
import signal
import sys
import threading
from pathlib import Path

import numpy as np
import warp as wp
from rich.table import Table

import abmpm
from abmpm.arguments import frames_arg as _frames_arg
from abmpm.arguments import threads_arg as _threads_arg
from abmpm.cli_common import EXIT_ERROR, EXIT_INTERRUPTED, EXIT_OK, check_threads_env
from abmpm.cli_common import esc as _esc
from abmpm.cli_common import port_arg as _port_arg
from abmpm.cli_common import stderr_console as _stderr
from abmpm.cli_common import stdout_console as _stdout
from abmpm.cli_post import add_parsers as add_post_parsers
from abmpm.cli_sweep import add_parsers as add_sweep_parsers
from abmpm.compare import PAPER_SCENES, compare, remeasure, run_paper
from abmpm.errors import OUT_OF_MEMORY_HINT, AbmpmError, OutOfMemory, SceneError, SimulationBlowUp, allocation_failure
from abmpm.io.outdir import CHECKPOINT_RE, CHECKPOINTS_DIR, numbered
from abmpm.io.writers.surface import surface_folder
from abmpm.io.writers.viewer import ViewOptions
from abmpm.post.viewer import Viewer
from abmpm.runner import run
from abmpm.runtime import init_warp, init_warp_silently
from abmpm.scene.loader import list_builtin_scenes, load_scene
from abmpm.scene.model import with_mode
from abmpm.sweep import parse_set

# --------------------------------------------------------------------------- commands


def _resume_command(args, out: Path) -> str:
    """The command that continues an interrupted ``abmpm run`` as it was asked for (the
    mode and the frame count are part of what the checkpoint belongs to)."""
    parts = ["abmpm", "run", args.scene, "--out", str(out)]
    for flag, value in (("--mode", args.mode), ("--frames", args.frames), ("--device", args.device),
                        ("--threads", args.threads)):
        if value:
            parts += [flag, str(value)]
    return shlex.join(parts + (["--no-preview"] if args.no_preview else []) + ["--resume"])


def _cmd_run(args) -> int:
    if args.threads:
        os.environ["ABMPM_THREADS"] = str(args.threads)  # read by the solver's launcher

    scene = load_scene(args.scene)
    if args.mode:
        scene = with_mode(scene, args.mode)
    default_out = Path("out") / (f"{scene.name}_{args.mode}" if args.mode else scene.name)
    out = Path(args.out) if args.out else default_out
    con = _stderr()
    label = args.scene if os.path.exists(args.scene) else f"{args.scene} (built-in)"
    if not args.quiet:
        con.print(f"[bold]abmpm[/bold] running [cyan]{_esc(label)}[/cyan] -> {_esc(out)}")
    try:
        summary = run(
            scene, out, device=args.device, frames=args.frames, resume=args.resume,
            preview=not args.no_preview, progress=not args.quiet, console=con,
            view=_view_options(args),
        )
    except KeyboardInterrupt:
        if numbered(out / CHECKPOINTS_DIR, CHECKPOINT_RE):
            print(f"interrupted; continue with: {_resume_command(args, out)}", file=sys.stderr)
        else:  # stopped while setting up (a large collider, the first split): nothing to resume from
            print("interrupted before the first checkpoint; run it again to start over", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (SimulationBlowUp, OutOfMemory) as exc:
        raise type(exc)(f"{exc} (frames up to then, a checkpoint and summary.json are in {out})") from None
    except SceneError as exc:
        # errors found while building the particles (body outside the domain, ...)
        # name the key; add the scene file when they do not name it already
        msg = str(exc)
        if os.path.exists(args.scene) and not msg.startswith(args.scene):
            raise SceneError(f"{args.scene}: {msg}") from None
        raise
    if not args.quiet:
        _print_summary(summary, out)
    return EXIT_OK


def _print_summary(s: dict, out: Path) -> None:
    con = _stdout()
    sps = s.get("steps_per_second")
    con.print(
        f"[green]done[/green]: {_esc(s['scene'])}: {s['particle_count']:,} particles, {s['frames']} frames "
        f"({s['sim_time']:.2f} s simulated), {s['steps']:,} steps"
        + (f" at {sps:,.0f} steps/s" if sps else "")
        + f" on {_esc(s['device'])} in {s['wall_seconds']:.1f} s"
    )
    outputs = s.get("outputs", {})
    for key in ("preview", "poster", "beauty", "beauty_poster", "energy_plot", "frames", "colliders", "checkpoints",
                "surfaces", "usd", "summary"):
        if key in outputs:
            con.print(f"  {key:<12} {_esc(out / outputs[key])}")


def _cmd_scenes(args) -> int:
    table = Table(title="built-in scenes (abmpm run NAME)")
    table.add_column("name", style="cyan", no_wrap=True)
    table.add_column("materials")
    table.add_column("duration", justify="right", no_wrap=True)
    table.add_column("description")
    for name, desc in list_builtin_scenes().items():
        try:
            sc = load_scene(name)
            mats = ", ".join(sorted({m.model for m in sc.materials}))
            table.add_row(_esc(name), mats, f"{sc.simulation.duration:g} s", _esc(desc))
        except AbmpmError as exc:  # a broken built-in must not hide the others
            table.add_row(name, "?", "?", f"[red]{_esc(exc)}[/red]")
    _stdout().print(table)
    return EXIT_OK


def _cmd_info(args) -> int:
    con = _stdout()
    con.print(f"abmpm   {getattr(abmpm, '__version__', '?')}")
    con.print(f"python  {platform.python_version()} ({_esc(sys.executable)})")
    con.print(f"numpy   {np.__version__}")
    try:
        init_warp()
        con.print(f"warp    {wp.config.version}")
        con.print("devices:")
        for d in wp.get_devices():
            extra = ""
            if d.is_cuda:
                mem = getattr(d, "total_memory", 0) or 0
                extra = f"  {getattr(d, 'name', '')}  {mem / 2**30:.1f} GiB" if mem else f"  {getattr(d, 'name', '')}"
            con.print(f"  {d.alias:<8}{extra}")
        if wp.get_cuda_device_count() == 0:
            con.print("  (no CUDA device: runs use the CPU)")
        con.print(f"kernel cache  {_esc(wp.config.kernel_cache_dir)}")
    except Exception as exc:  # info must work even when Warp is broken
        con.print(f"warp    unavailable ({type(exc).__name__}: {_esc(exc)})")
    for mod, label in (("pxr", "usd-core"), ("imageio_ffmpeg", "imageio-ffmpeg")):
        con.print(f"{label:<15} {'installed' if importlib.util.find_spec(mod) else 'not installed'}")
    return EXIT_OK


def _view_options(args):
    """abmpm run --view: the live view, served on after the run until Ctrl-C."""
    if not args.view:
        return None

    return ViewOptions(port=args.view_port, keep_open=True)


def _cmd_view(args) -> int:
    viewer = Viewer(args.dir, host=args.host, port=args.port)
    try:
        _stdout().print(f"viewing {_esc(args.dir)} at [bold]{_esc(viewer.url)}[/bold] (Ctrl-C to stop)")
        viewer.wait()
    except KeyboardInterrupt:
        pass  # the normal way to stop serving
    finally:
        viewer.close()
    return EXIT_OK


def _cmd_surface(args) -> int:
    info = surface_folder(args.dir)
    if not args.quiet:
        usd = ", particles.usd rewritten with them" if info["usd"] else ""
        _stdout().print(
            f"[green]meshed[/green] {info['frames']} frames -> {_esc(Path(args.dir) / 'surfaces')} "
            f"({info['triangles']} triangles, {info['seconds_per_frame']:.3f} s a frame{usd})"
        )
    return EXIT_OK


def _cmd_compare(args) -> int:
    """``abmpm compare SCENE`` and ``abmpm paper``: the modes of a scene side by side."""
    if args.threads:
        os.environ["ABMPM_THREADS"] = str(args.threads)
    modes = tuple(dict.fromkeys(args.modes or ("original", "adaptive", "finest")))  # each mode once
    con = _stderr()

    def on_run(i, n, scene, mode, run_dir):
        if not args.quiet:
            con.print(f"[{i}/{n}] {scene} {mode} -> {run_dir}", markup=False)

    overrides = {}
    if args.set:
        for key, values in parse_set(args.set).items():
            if len(values) != 1:
                raise AbmpmError(f"--set {key}: one value here (abmpm sweep runs several)")
            overrides[key] = values[0]
    common = dict(modes=modes, device=args.device, frames=args.frames, overrides=overrides,
                  progress=not args.quiet, on_run=on_run)
    if args.command == "paper":
        out = Path(args.out) if args.out else Path("out") / ("paper_quick" if args.quick else "paper")
    else:
        scene = load_scene(args.scene)  # unknown scene: one-line error before any run
        out = Path(args.out) if args.out else Path("out") / f"{scene.name}_compare"
    if args.remeasure:  # the runs already there, measured again: nothing runs
        records = remeasure(out)
        if not records:
            raise AbmpmError(f"{out}: no runs to measure again (no table1.json of abmpm {args.command})")
    elif args.command == "paper":
        records = run_paper(scenes=tuple(args.scenes) if args.scenes else _paper_scenes(),
                            out=out, quick=args.quick, window=args.window, **common)
    else:
        records = compare(scene, out=out, quick=args.quick, **common)
    if not args.quiet:
        for r in records:
            leaked = (r.get("leaks") or {}).get("total")
            sps = r.get("steps_per_second")
            _stdout().print(f"{_esc(r['scene'])} {r['mode']}: {r['status']}, "
                            f"{r.get('particles_end') or 0:,} particles, "
                            f"{'-' if sps is None else f'{sps:.1f}'} steps/s, leaked {'-' if leaked is None else leaked}")
        _stdout().print(f"results: {_esc(out / 'table1.json')}, {_esc(out / 'report.md')}")
    failed = [r for r in records if r.get("status") != "completed"]
    if failed:
        print(f"error: {len(failed)} of {len(records)} runs did not complete; see {out / 'report.md'}", file=sys.stderr)
        return EXIT_ERROR
    return EXIT_OK


def _paper_scenes() -> tuple:
    return PAPER_SCENES


def _cmd_bench(args) -> int:
    missing = False
    try:
        run_bench = importlib.import_module("abmpm.bench").run_bench
    except ModuleNotFoundError as exc:
        if not (exc.name or "").startswith("abmpm"):
            raise  # the benchmark exists but one of its dependencies does not
        missing = True
    except AttributeError:
        missing = True
    if missing:
        print("error: the benchmark is not available in this version of abmpm "
              "(abmpm.bench.run_bench is missing)", file=sys.stderr)
        return EXIT_ERROR
    result = run_bench(args.bench_args) if args.bench_args else run_bench()
    return result if isinstance(result, int) else EXIT_OK


# --------------------------------------------------------------------------- parser


class _Parser(argparse.ArgumentParser):
    """argparse with one-line usage errors: ``abmpm: error: ...`` and exit status 2
    (no usage block: ``abmpm --help`` / ``abmpm run --help`` show it)."""

    def error(self, message: str):
        message = " ".join(str(message).split())
        self.exit(EXIT_ERROR, f"abmpm: error: {message} (see: {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="abmpm",
        description="Adaptive boundary MLS-MPM simulator (NVIDIA Warp, CPU and CUDA).",
    )
    p.add_argument("--version", action="version", version=f"abmpm {getattr(abmpm, '__version__', '?')}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    r = sub.add_parser("run", help="run a scene (a .toml file or a built-in name)")
    r.add_argument("scene", metavar="SCENE", help="scene file (.toml) or built-in name (see `abmpm scenes`)")
    r.add_argument("--out", "-o", metavar="DIR", help="output folder (default: out/<scene name>/)")
    r.add_argument("--device", "-d", metavar="DEVICE",
                   help="cpu, cuda or cuda:N (default: the scene's, else cuda when available)")
    r.add_argument("--frames", "-n", type=_frames_arg, metavar="N", help="number of frames (default: duration * fps)")
    r.add_argument("--mode", choices=["original", "adaptive", "finest"],
                   help="refinement mode, overriding the scene's (default out: out/<scene>_<mode>/)")
    r.add_argument("--resume", action="store_true", help="continue from the latest checkpoint in the output folder")
    r.add_argument("--no-preview", action="store_true", help="do not render preview.mp4 / preview.png")
    r.add_argument("--view", action="store_true",
                   help="watch the run in the web browser (needs viser); serves on after the run until Ctrl-C")
    r.add_argument("--view-port", type=_port_arg, default=8080, metavar="N",
                   help="port of --view (default 8080, else the next free one)")
    r.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary")
    r.add_argument("--threads", "-j", type=_threads_arg, metavar="N",
                   help="CPU threads for the step (default: $ABMPM_THREADS, else every core)")
    r.set_defaults(func=_cmd_run)

    s = sub.add_parser("scenes", help="list the built-in scenes")
    s.set_defaults(func=_cmd_scenes)

    i = sub.add_parser("info", help="versions and available devices")
    i.set_defaults(func=_cmd_info)

    add_post_parsers(sub)  # render (preview or --beauty), blender
    add_sweep_parsers(sub)  # sweep

    v = sub.add_parser("view", help="browse a run's frames in the web browser (needs viser)")
    v.add_argument("dir", metavar="DIR", help="output folder of a run")
    v.add_argument("--port", "-p", type=_port_arg, default=8080, metavar="N",
                   help="port to serve on (default 8080, else the next free one)")
    v.add_argument("--host", default="127.0.0.1", metavar="HOST",
                   help="address to serve on (default 127.0.0.1; 0.0.0.0 for other machines)")
    v.set_defaults(func=_cmd_view)

    m = sub.add_parser("surface", help="surface meshes (PLY, and into the USD) of a finished run's frames")
    m.add_argument("dir", metavar="DIR", help="output folder of a run")
    m.add_argument("--quiet", "-q", action="store_true", help="print nothing")
    m.set_defaults(func=_cmd_surface)

    for name in ("compare", "paper"):
        if name == "compare":
            c = sub.add_parser("compare", help="run a scene in original, adaptive and finest mode and compare them",
                               description="Run SCENE in each mode into DIR/<scene>/<mode>/ and write "
                                           "DIR/table1.json and DIR/report.md (particles, steps/s, the scene's "
                                           "outcome figures, leaked particles, plots and a montage).")
            c.add_argument("scene", metavar="SCENE", help="scene file (.toml) or built-in name")
        else:
            c = sub.add_parser("paper", help="the paper's five experiments (Table 1) in three modes, with a report",
                               description="Run the paper scenes (paper_panel, paper_hourglass, paper_cut, "
                                           "paper_bunny_split, paper_jelly) in each mode and write "
                                           "DIR/table1.json and DIR/report.md next to the paper's Table 1.")
            c.add_argument("--scenes", nargs="+", metavar="SCENE", help="which paper scenes (default: all five)")
            c.add_argument("--window", type=float, metavar="SECONDS",
                           help="run each scene to SECONDS of simulated time after its contact "
                                "(abmpm.compare.PAPER_CONTACT) and time that window apart, e.g. 0.2")
        c.add_argument("--modes", nargs="+", metavar="MODE",
                       help="original, adaptive and/or finest (default: all three)")
        c.add_argument("--quick", action="store_true",
                       help="coarser, shorter versions of the paper scenes (~7 min for all on 2 CPU cores)")
        c.add_argument("--frames", "-n", type=_frames_arg, metavar="N", help="frames per run (default: duration * fps)")
        c.add_argument("--set", "-s", dest="set", action="append", default=[], metavar="KEY=VALUE",
                       help="change a scene setting in every run, e.g. simulation.refinement.merge=true (repeatable)")
        c.add_argument("--out", "-o", metavar="DIR",
                       help="output folder (default: out/<scene>_compare/ or out/paper[_quick]/)")
        c.add_argument("--device", "-d", metavar="DEVICE", help="cpu, cuda or cuda:N")
        c.add_argument("--threads", "-j", type=_threads_arg, metavar="N", help="CPU threads for the step")
        c.add_argument("--quiet", "-q", action="store_true", help="no progress")
        c.add_argument("--remeasure", action="store_true",
                       help="run nothing: measure the runs already in the output folder again and rewrite its "
                            "table, figures and report (after a measure changed)")
        c.set_defaults(func=_cmd_compare)

    b = sub.add_parser("bench", help="performance benchmark (options: abmpm bench --help-bench)",
                       add_help=False)
    b.set_defaults(func=_cmd_bench, bench_args=[])
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``abmpm``; returns the exit status (0 ok, 2 error, 130 interrupted)."""
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
        if extra and getattr(args, "func", None) is _cmd_bench:
            args.bench_args = ["--help" if a == "--help-bench" else a for a in extra]  # the benchmark's own options
        elif extra:
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
    except SystemExit as exc:  # --help, --version, usage errors
        return int(exc.code) if isinstance(exc.code, int) else EXIT_ERROR
    init_warp_silently()
    previous = None
    if threading.current_thread() is threading.main_thread():
        # a SIGTERM (a job scheduler, `timeout`, `kill`) ends a run as Ctrl-C does: its
        # summary says "interrupted" and how to resume
        previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        if not getattr(args, "threads", None):
            check_threads_env()  # ABMPM_THREADS, read by every run that is not given --threads
        return args.func(args)
    except AbmpmError as exc:
        lines = str(exc).splitlines() or [type(exc).__name__]
        print(f"error: {lines[0]}", file=sys.stderr)
        for line in lines[1:]:
            print(f"error: {line}", file=sys.stderr)
        return EXIT_ERROR
    except (MemoryError, RuntimeError) as exc:
        if not allocation_failure(exc):
            raise
        detail = f" ({exc})" if str(exc) else ""
        print(f"error: out of memory{detail}; {OUT_OF_MEMORY_HINT}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _terminated(signum, frame):
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
