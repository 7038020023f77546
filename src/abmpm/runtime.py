"""What every layer above ``sim/`` needs of the machine: Warp started once and
quietly, the device a run asks for, and the time step's formula (CFL and viscosity).

``scene/`` (its feasibility checks) and ``simulation.py`` both import this; it
imports nothing of abmpm but the errors, so neither has to import the other.
"""

from __future__ import annotations

import os
import re
import sys

import warp as wp

from .errors import AbmpmError

VERBOSE_ENV = "ABMPM_VERBOSE"  # set: Warp's own start-up and module-load messages stay on
DEBUG_ENV = "ABMPM_WARP_DEBUG"  # set: Warp's debug build (every array access bounds-checked; slow)

_warp_ready = False

# Explicit viscosity (Newtonian, or Kelvin-Voigt damping) diffuses momentum by nu dt / dx^2
# of a cell per step: a fluid box at rest (dx = 0.05, eta up to 3000 Pa s, 0.6 s) ran
# at nu dt / dx^2 = 0.2 and 0.4 and blew up at 0.6, 0.8 and 1.2, so half the last stable
# measured value is kept (docs/method.md, "Time step").
VISCOUS_CFL = 0.2
# A CFL step below this fraction of the step at rest (speed 0) is a blow-up: the
# fastest particle moves ~1000x the material's wave speed.
MIN_DT_FRACTION = 1.0e-3


def cfl_time_step(cfl: float, max_dt: float, dx: float, signal_speed: float, viscosity: float = 0.0) -> float:
    """dt = min(max_dt, cfl dx / (wave speed + particle speed)): a signal crosses at
    most ``cfl`` of a cell per step; and with a kinematic ``viscosity`` nu (m^2/s, the
    largest eta / rho of the materials) at most VISCOUS_CFL dx^2 / nu, the limit of
    explicit viscosity."""
    dt = min(max_dt, cfl * dx / signal_speed)
    return min(dt, VISCOUS_CFL * dx * dx / viscosity) if viscosity > 0.0 else dt


def init_warp() -> None:
    """Start Warp once: quiet unless ``ABMPM_VERBOSE``, its debug build under
    ``ABMPM_WARP_DEBUG``."""
    global _warp_ready
    if _warp_ready:
        return
    if not os.environ.get(VERBOSE_ENV) and hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no module-load chatter
    wp.config.quiet = True
    if os.environ.get(DEBUG_ENV):
        wp.config.mode = "debug"
        wp.config.verify_fp = False
    wp.init()
    _warp_ready = True


def init_warp_silently() -> None:
    """``init_warp`` with the process's stderr muted while Warp starts: its native code
    prints "could not load the CUDA driver" on every start on a machine without a GPU
    (``abmpm info`` says the same in plain words). For the command line and workers."""
    if os.environ.get(VERBOSE_ENV):
        init_warp()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            try:
                init_warp()
            finally:
                os.dup2(saved, 2)
    finally:
        os.close(saved)


# the device names choose_device understands ("" and "auto": a GPU when present)
DEVICE_NAME = re.compile(r"(auto|cpu|cuda(:\d+)?)?")


def device_name_problem(requested: str) -> str | None:
    """Why ``requested`` is no device name at all (whether this machine has it is
    choose_device's question), or None."""
    return None if DEVICE_NAME.fullmatch(requested) else f"unknown device {requested!r} (use 'cpu', 'cuda' or 'cuda:N')"


def choose_device(requested: str | None) -> str:
    """'cuda' when a GPU is present, else 'cpu'; an explicit request is honoured or refused."""
    init_warp()
    has_cuda = wp.get_cuda_device_count() > 0
    if requested in (None, "", "auto"):
        return "cuda:0" if has_cuda else "cpu"
    if requested == "cpu":
        return "cpu"
    if requested == "cuda" or requested.startswith("cuda:"):
        if not has_cuda:
            raise AbmpmError(f"device {requested!r} requested but no CUDA device is available (use 'cpu')")
        if requested == "cuda":
            return "cuda:0"
        index = requested[len("cuda:"):]
        count = wp.get_cuda_device_count()
        if not requested.startswith("cuda:") or not index.isdigit() or int(index) >= count:
            raise AbmpmError(f"unknown device {requested!r}: this machine has cuda:0 to cuda:{count - 1}")
        return requested
    raise AbmpmError(device_name_problem(requested))
