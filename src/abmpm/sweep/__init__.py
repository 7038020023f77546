"""Wedges (parameter sweeps): run a scene once per combination of set values.

``abmpm sweep dam_break --set simulation.dx=0.02,0.01 --set simulation.refinement.mode=original,adaptive``
runs the Cartesian product of the values (like a Houdini wedge), each into a folder
of its own named from the values, and writes one row per run to ``sweep.csv`` and
``sweep.json``::

    DIR/
        dx=0.02,mode=original/      a normal run folder (summary.json, frames/, ...)
        dx=0.02,mode=adaptive/
        ...
        sweep.csv                   one row per run: values, status, headline figures
        sweep.json                  the same rows, with the sweep's definition

A value is parsed as a TOML value (``0.02``, ``1e-3``, ``true``, ``"text"``,
``[0, 1, 0]``); anything TOML does not parse is a bare string (``adaptive``).
Every combination is applied to the scene and validated with the scene model before
anything runs, so a misspelt key or a refused value is one error naming the key.

The runs go one after another in this process, or (``ray=...``) as Ray tasks that
write into the same folder: on a cluster of several machines, ``DIR`` must be on a
filesystem every node sees. A run that blows up or fails is recorded in its row and
the sweep goes on.

The modules, each name below re-exported here:

* :mod:`~abmpm.sweep.plan`: ``--set`` keys and values, overrides applied to the
  scene document, validation, folder names, :class:`SweepPlan`, :func:`plan_sweep`
  and :func:`feasible_on`;
* :mod:`~abmpm.sweep.execute`: :func:`run_one` and its headline row, the
  ``sweep.csv`` / ``sweep.json`` writer, the local loop and :func:`run_sweep`;
* :mod:`~abmpm.sweep.cluster`: everything Ray (import, reachability of an address,
  connecting, the loop of Ray tasks).

The local loop and the Ray task call ``run_one`` as it is in
:mod:`~abmpm.sweep.execute` (``abmpm.sweep.execute.run_one``), so replacing it
there takes effect.
"""

from abmpm.sweep.cluster import RAY_MISSING, import_ray
from abmpm.sweep.execute import CSV_FILE, JSON_FILE, columns, headline, run_one, run_sweep, write_results
from abmpm.sweep.plan import (
    SceneSource,
    SweepPlan,
    apply_overrides,
    feasible_on,
    folder_name,
    format_value,
    key_text,
    parse_key,
    parse_set,
    parse_values,
    plan_sweep,
    scene_source,
)

__all__ = [
    "SceneSource",
    "SweepPlan",
    "parse_set",
    "parse_values",
    "parse_key",
    "apply_overrides",
    "plan_sweep",
    "feasible_on",
    "run_one",
    "run_sweep",
    "write_results",
    "CSV_FILE",
    "JSON_FILE",
    "RAY_MISSING",
    # the other public names of the modules
    "key_text",
    "format_value",
    "scene_source",
    "folder_name",
    "headline",
    "columns",
    "import_ray",
]
