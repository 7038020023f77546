"""Argument types the commands share (``abmpm`` and ``abmpm bench``, which parses its
own options): whole counts, finite numbers above 0, and threads no more than this
process's CPU cores."""

from __future__ import annotations

import argparse
import math

from abmpm.scene.checks import MAX_FRAMES
from abmpm.sim.parallel import default_threads


def positive_int(text: str, what: str) -> int:
    """An argparse type: a whole number of ``what``, at least 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of {what}, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def int_between(text: str, what: str, lo: int, hi: int) -> int:
    """An argparse type: ``what`` (e.g. "a port number"), a whole number from lo to hi."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not lo <= n <= hi:
        raise argparse.ArgumentTypeError(f"{what} is between {lo} and {hi}, got {n}")
    return n


def positive_float(text: str, what: str) -> float:
    """An argparse type: ``what`` (e.g. "a number of seconds"), finite and above 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not math.isfinite(x) or x <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number above 0, got {text}")
    return x


def threads_arg(text: str) -> int:
    """--threads N: at most the CPU cores this process may use (each thread beyond the
    first keeps its own copy of the grids' sums)."""
    n = positive_int(text, "threads")
    cores = default_threads(from_env=False)
    if n > cores:
        raise argparse.ArgumentTypeError(f"{n} threads: more than the {cores} CPU cores this process may use")
    return n


def frames_arg(text: str) -> int:
    """--frames N, at most the MAX_FRAMES a scene's duration * fps may ask for"""
    n = positive_int(text, "frames")
    if n > MAX_FRAMES:
        raise argparse.ArgumentTypeError(f"{n} frames: more than {MAX_FRAMES:.0e}")
    return n
