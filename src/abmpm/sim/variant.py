"""Compile-time variants of the transfer kernels.

A pass of the step (``sim/p2g.py``, ``sim/g2p.py``) is written once and compiled
for what a scene needs: with or without CPIC (colliders), for the material models
the scene uses (``materials.dispatch``). On Warp's CPU backend code that is skipped
at run time still costs time, so a variant that does not need a branch does not
carry it. Each variant is compiled the first time a scene asks for it.
"""

from __future__ import annotations

import warp as wp

from .materials import ALL_MODELS


def variant(name: str, *flags: bool, models: tuple[int, ...] = ALL_MODELS):
    """Decorator: the kernel ``name`` for ``flags`` and ``models``, in a module of its
    own and named after its variant (e.g. ``p2g_dense_1_m0``): Warp's CPU graph replay
    finds kernels by name, so variants sharing the closure's name all replayed as the
    last; a module each means a scene compiles the few it uses, not all of them for
    every model (27 s on this CPU with a cold kernel cache)."""

    def kernel(f):
        f.__qualname__ = name + "_" + "".join(str(int(flag)) for flag in flags) + "_m" + "".join(map(str, models))
        return wp.kernel(f, enable_backward=False, module="unique")

    return kernel
