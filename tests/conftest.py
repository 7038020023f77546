import os

import pytest

# Keep Warp quiet and on the CPU in tests; CUDA tests opt in explicitly.
os.environ.setdefault("WARP_QUIET", "1")


@pytest.fixture(scope="session")
def cuda_available():
    import warp as wp

    from abmpm.simulation import init_warp

    init_warp()
    return wp.get_cuda_device_count() > 0


# Under pytest-xdist every worker is a process of its own: give each an equal share
# of the cores for the solver's CPU threads (tests that measure threading set theirs).
if "PYTEST_XDIST_WORKER_COUNT" in os.environ and "ABMPM_THREADS" not in os.environ:
    _workers = int(os.environ["PYTEST_XDIST_WORKER_COUNT"])
    os.environ["ABMPM_THREADS"] = str(max(1, (os.cpu_count() or 1) // _workers))


class RegistryCopy:
    """A copy of the abmpm package in ``root`` in which a test adds one module to a
    registry, and runs a check script on that copy in a fresh interpreter."""

    def __init__(self, root):
        import shutil
        from pathlib import Path

        import abmpm

        self.root = Path(root)
        self.package = self.root / "abmpm"
        shutil.copytree(Path(abmpm.__file__).parent, self.package, ignore=shutil.ignore_patterns("__pycache__"))

    def register(self, folder: str, name: str, text: str, last: str) -> None:
        """Write ``folder/name.py`` and append ``name`` after ``last`` in the folder's
        ``MODULES``: one new file and exactly one changed line."""
        (self.package / folder / f"{name}.py").write_text(text)
        init = self.package / folder / "__init__.py"
        lines = init.read_text().splitlines()
        edited = [ln.replace(f'"{last}")', f'"{last}", "{name}")') if ln.startswith("MODULES = ") else ln
                  for ln in lines]
        assert sum(a != b for a, b in zip(lines, edited)) == 1  # exactly one line changed
        init.write_text("\n".join(edited) + "\n")

    def run(self, check: str, *args, timeout: int = 900) -> dict:
        """Run ``check`` (a script; Warp kernels must live in a file) on the copy; the
        dict it printed as ``RESULT <json>``."""
        import json
        import subprocess
        import sys

        script = self.root / "check.py"
        script.write_text(check)
        run = subprocess.run([sys.executable, str(script), *map(str, args)], cwd=self.root,
                             env={**os.environ, "PYTHONPATH": str(self.root)}, capture_output=True, text=True,
                             timeout=timeout)
        line = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
        assert run.returncode == 0 and line, run.stdout[-3000:] + run.stderr[-3000:]
        return json.loads(line[0][len("RESULT "):])


@pytest.fixture
def registry_copy(tmp_path):
    """A copy of the package to add a registry module to (``RegistryCopy``)."""
    return RegistryCopy(tmp_path)


def _poison_velocity(sim, ids=None):
    """What a blow-up leaves: NaN velocities (of the particles ``ids``, else all) written
    into the device state itself (``set_particles`` refuses non-finite values)."""
    import numpy as np

    v = sim._state.v.numpy()
    if ids is None:
        v[:] = np.nan
    else:
        v[np.isin(sim._state.id.numpy(), ids)] = np.nan
    sim._state.v.assign(v)


@pytest.fixture
def poison_velocity():
    return _poison_velocity


# A scene of a few hundred water particles in a small box, for tests of what a run does
# around the simulation (its errors, notes and files), not of the physics.
SMALL_WATER_SCENE = """\
name = "small"
[simulation]
domain_max = [0.4, 0.4, 0.4]
dx = 0.05
duration = 0.1
fps = 30.0
[[materials]]
name = "water"
model = "fluid"
[[bodies]]
shape = "box"
material = "water"
min = [0.05, 0.0, 0.05]
max = [0.2, 0.15, 0.2]
"""


@pytest.fixture
def small_water_scene():
    """The TOML text of SMALL_WATER_SCENE."""
    return SMALL_WATER_SCENE
