"""The ``abmpm render`` and ``abmpm blender`` commands: pictures of a finished run.

    abmpm render DIR                 re-render the splat preview (fast)
    abmpm render DIR --beauty        path-trace beauty.mp4 / beauty.png with Mitsuba 3
    abmpm blender DIR                DIR/abmpm.blend: the run as an animated Blender scene

:func:`add_parsers` adds them to the parser of :mod:`abmpm.cli`, which runs them
and turns their errors into one line.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from abmpm.arguments import positive_int, threads_arg
from abmpm.errors import AbmpmError
from abmpm.io.blender import write_blend
from abmpm.io.writers.surface import surface_folder
from abmpm.post.beauty import BeautySettings, render_beauty
from abmpm.runner import render_folder

__all__ = ["add_parsers"]

BEAUTY_HELP = (
    "path-trace beauty.mp4 and beauty.png of the run's surface meshes and colliders with Mitsuba 3 "
    "(pip install -e \".[render]\"; meshes the surfaces first when the run has none). Slow on a CPU: "
    "the defaults (640x360, 16 spp) take about 5 s a frame on one CPU core (4 minutes for the 46 frames "
    "of the letter_panel demo, about half that on 2 cores); the CUDA variant is used where a GPU works"
)


def _samples(text: str) -> int:
    return positive_int(text, "samples per pixel")


def _stride(text: str) -> int:
    return positive_int(text, "frames")


def _size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x360, got {text!r}") from None
    if not sep or min(size) < 8 or max(size) > 8192:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT between 8 and 8192 pixels, got {text!r}")
    return size


def _cmd_render(args) -> int:
    if not args.beauty:
        extra = [f for f, v in (("--spp", args.spp), ("--size", args.size), ("--stride", args.stride),
                                ("--variant", args.variant), ("--colliders", args.colliders)) if v]
        if extra:
            raise AbmpmError(f"{', '.join(extra)}: only with --beauty")

        info = render_folder(args.dir, progress=not args.quiet)
        files = f"{info['preview']}, {info['poster']}"
    else:
        base = BeautySettings()
        w, h = args.size or (base.width, base.height)
        settings = BeautySettings(width=w, height=h, spp=args.spp or base.spp, stride=args.stride or 1,
                                  variant=args.variant, colliders=args.colliders, threads=args.threads)
        info = render_beauty(args.dir, settings, progress=not args.quiet, mesh=surface_folder)
        files = f"{info['beauty']}, {info['poster']} ({info['variant']}, {info['seconds_per_frame']:.1f} s a frame)"
    if not args.quiet:
        Console(highlight=False).print(f"[green]rendered[/green] {info['frames']} frames -> {escape(files)}")
    return 0


def _cmd_blender(args) -> int:
    info = write_blend(args.dir, args.output)
    if not args.quiet:
        Console(highlight=False).print(
            f"[green]wrote[/green] {escape(info['blend'])}: frames {info['frame_start']}-{info['frame_end']} "
            f"at {info['fps']:g} fps, {info['objects']} objects"
        )
    return 0


def add_parsers(sub) -> None:
    """Add ``render`` and ``blender`` to the subparsers ``sub`` of ``abmpm``."""
    d = sub.add_parser("render", help="re-render the preview of a run from its frames (--beauty: path-traced)",
                       description="Re-render preview.mp4 / preview.png of a run from its frames. With "
                                   "--beauty: " + BEAUTY_HELP + ".")
    d.add_argument("dir", metavar="DIR", help="output folder of a run")
    d.add_argument("--beauty", action="store_true", help=BEAUTY_HELP)
    d.add_argument("--spp", type=_samples, metavar="N", help="--beauty: samples per pixel (default 16)")
    d.add_argument("--size", type=_size, metavar="WxH", help="--beauty: image size (default 640x360)")
    d.add_argument("--stride", type=_stride, metavar="N",
                   help="--beauty: render every N-th surface frame (default 1: all)")
    d.add_argument("--variant", metavar="NAME",
                   help="--beauty: Mitsuba variant (default: cuda_ad_rgb where it works, else scalar_rgb)")
    d.add_argument("--colliders", choices=["metal", "glass"],
                   help="--beauty: the colliders' look (default: the scene's output.beauty_colliders, metal)")
    d.add_argument("--threads", "-j", type=threads_arg, metavar="N",
                   help="--beauty: CPU threads (default: $ABMPM_THREADS, else every core)")
    d.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    d.set_defaults(func=_cmd_render)

    b = sub.add_parser("blender", help="write the run as an animated Blender scene (needs bpy)",
                       description="Write DIR/abmpm.blend: the run's surface meshes, colliders and particles "
                                   "as PLY sequences with materials, the frame range and fps of the run, the "
                                   "preview's camera and a light (pip install -e \".[blender]\"). Inside "
                                   "Blender, run src/abmpm/io/blender.py instead (docs/rendering.md).")
    b.add_argument("dir", metavar="DIR", help="output folder of a run")
    b.add_argument("--output", "-o", metavar="FILE", type=Path, help="the .blend file (default DIR/abmpm.blend)")
    b.add_argument("--quiet", "-q", action="store_true", help="print nothing")
    b.set_defaults(func=_cmd_blender)
