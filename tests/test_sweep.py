"""Wedges (abmpm sweep): --set parsing and up-front validation, folder names, a local
2x2 sweep with its sweep.csv / sweep.json, a blow-up recorded in its row, the CLI,
and the same sweep as Ray tasks on a local Ray instance (bit-identical frames)."""

from __future__ import annotations

import csv
import json
import os
import sys
import time

import numpy as np
import pytest

from abmpm.cli import main
from abmpm.errors import AbmpmError, SceneError
from abmpm.simulation import Simulation
from abmpm.sweep import (
    RAY_MISSING,
    apply_overrides,
    folder_name,
    import_ray,
    parse_key,
    parse_set,
    parse_values,
    plan_sweep,
    run_one,
    run_sweep,
)

# Water and a jelly ball in a 0.4 m box: 1,768 particles at dx=0.04, 4,064 at 0.03;
# a 2-frame run takes about a second on one thread.
TINY = {
    "name": "tiny",
    "simulation": {"domain_max": [0.4, 0.4, 0.4], "dx": 0.05, "duration": 0.2},
    "materials": [
        {"name": "water", "model": "fluid"},
        {"name": "jelly", "model": "elastic", "youngs_modulus": 1.0e4},
    ],
    "bodies": [
        {"shape": "box", "material": "water", "min": [0.0, 0.0, 0.0], "max": [0.15, 0.2, 0.4]},
        {"shape": "sphere", "material": "jelly", "center": [0.28, 0.25, 0.2], "radius": 0.07},
    ],
    "output": {"preview": False},
}
VALUES = {"simulation.dx": [0.04, 0.03], "simulation.refinement.mode": ["original", "adaptive"]}
NAMES = ["dx=0.04,mode=original", "dx=0.04,mode=adaptive", "dx=0.03,mode=original", "dx=0.03,mode=adaptive"]

TINY_TOML = """
name = "tiny"
[simulation]
domain_max = [0.4, 0.4, 0.4]
dx = 0.05
duration = 0.2
[[materials]]
name = "water"
model = "fluid"
[[bodies]]
shape = "box"
material = "water"
min = [0.0, 0.0, 0.0]
max = [0.15, 0.2, 0.4]
[output]
preview = false
"""


# --------------------------------------------------------------------------- parsing


def test_values_are_toml_scalars_else_strings():
    assert parse_values("k", "0.02,0.01") == [0.02, 0.01]
    vals = parse_values("k", "1, 2.5, 1e-3, true, false, original, \"quoted, with comma\", 'lit'")
    assert vals == [1, 2.5, 1e-3, True, False, "original", "quoted, with comma", "lit"]
    assert [type(v) for v in vals[:5]] == [int, float, float, bool, bool]
    # vectors keep their commas; a quoted number stays a string
    assert parse_values("k", "[0, -9.81, 0],[0,-1,0]") == [[0, -9.81, 0], [0, -1, 0]]
    assert parse_values("k", '"0.5"') == ["0.5"]


def test_parse_set_keys_and_order():
    got = parse_set(["simulation.dx=0.02,0.01", "materials.0.viscosity=0,1e-3", "output.preview=true"])
    assert list(got) == ["simulation.dx", "materials[0].viscosity", "output.preview"]
    assert got["materials[0].viscosity"] == [0, 0.001] and got["output.preview"] == [True]
    assert parse_key("bodies[1].velocity") == ["bodies", 1, "velocity"]


@pytest.mark.parametrize(
    "items, match",
    [
        (["simulation.dx"], r"--set simulation.dx: expected KEY=V1,V2"),
        (["simulation.dx="], r"--set simulation.dx: no values given"),
        (["simulation.dx=  "], r"--set simulation.dx: no values given"),
        (["simulation.dx=0.1,,0.2"], r"--set simulation.dx: value 2 is empty"),
        (["simulation.dx=0.1,0.1"], r"--set simulation.dx: value 0.1 is given twice"),
        (["simulation.dx=0.1", "simulation.dx=0.2"], r"--set simulation.dx: given twice"),
        (["=1"], r"--set: empty key"),
        (["simulation..dx=1"], r"--set simulation..dx: not a key path"),
        ([], r"nothing to sweep"),
    ],
)
def test_parse_set_errors_name_the_key(items, match):
    with pytest.raises(AbmpmError, match=match):
        parse_set(items)


@pytest.mark.parametrize(
    "values, message",
    [
        ({"simulation.dxx": [0.1]}, "--set simulation.dxx=0.1: simulation.dxx: unknown key"),
        ({"simulation.dx": ["abc"]}, "--set simulation.dx=abc: simulation.dx: expected a number, got 'abc'"),
        ({"simulation.dx": [0.02, -1]}, "--set simulation.dx=-1: simulation.dx: must be > 0"),
        ({"simulation.refinement.mode": ["original", "coarse"]},
         "--set simulation.refinement.mode=coarse: simulation.refinement.mode: must be one of "
         "original, adaptive, finest, got 'coarse'"),
        ({"output.preview": ["yes"]}, "--set output.preview=yes: output.preview: expected true or false, got 'yes'"),
        ({"materials[0].youngs_modulus": [1.0]},
         "--set materials[0].youngs_modulus=1.0: materials[0].youngs_modulus: unknown key"),
        ({"materials[5].density": [1.0]}, "--set materials[5].density: materials has 2 entries (index 0 to 1)"),
        ({"materials.density": [1.0]},
         "--set materials.density: materials is a list; give the index of an entry, e.g. materials[0].density"),
        ({"simulation.dx.step": [1]}, "--set simulation.dx.step: simulation.dx is a number, not a table"),
        ({"simulation.dx": []}, "--set simulation.dx: no values given (expected simulation.dx=V1,V2,...)"),
    ],
)
def test_bad_key_or_value_is_refused_before_anything_runs(tmp_path, values, message):
    with pytest.raises(AbmpmError) as exc:
        run_sweep(TINY, values, tmp_path / "sweep", frames=1)
    assert str(exc.value) == message
    assert not (tmp_path / "sweep").exists()  # nothing ran, nothing was written


def test_every_combination_is_validated():
    # each value is fine with the scene's own settings; together dx=0.03 leaves 3 cells
    scene = apply_overrides(TINY, {"simulation.dx": 0.02})
    values = {"simulation.dx": [0.02, 0.03], "simulation.domain_max": [[0.4, 0.4, 0.4], [0.1, 0.1, 0.1]]}
    with pytest.raises(SceneError, match=r"^--set simulation.dx=0.03 --set simulation.domain_max=\[0.1, 0.1, 0.1\]: "
                                         r"simulation.dx: dx=0.03 leaves fewer than 4 cells"):
        plan_sweep(scene, values)


def test_up_front_check_is_given_each_validated_scene():
    seen = []
    plan = plan_sweep(TINY, VALUES, check=lambda sc, combo: seen.append((sc.simulation.dx, sc.simulation.refinement.mode)))
    assert seen == [(0.04, "original"), (0.04, "adaptive"), (0.03, "original"), (0.03, "adaptive")]
    assert [name for name, _ in plan.runs] == NAMES
    assert plan.runs[1][1] == {"simulation.dx": 0.04, "simulation.refinement.mode": "adaptive"}


def test_overrides_make_missing_tables_and_leave_the_scene_alone():
    before = json.dumps(TINY, sort_keys=True)
    data = apply_overrides(TINY, {"simulation.walls.y_min.friction": 0.5, "materials[1].density": 1200.0})
    assert data["simulation"]["walls"] == {"y_min": {"friction": 0.5}}
    assert data["materials"][1]["density"] == 1200.0
    assert json.dumps(TINY, sort_keys=True) == before


def test_folder_names_are_short_unique_and_safe():
    short = {"simulation.dx": "dx", "a": "a"}
    assert folder_name({"simulation.dx": 0.02, "a": "x/y z"}, short) == "dx=0.02,a=x_y_z"
    assert folder_name({"simulation.dx": [0, -1, 0.5]}, short) == "dx=0_-1_0.5"
    # the same last name twice: the keys keep enough of their path to differ
    plan = plan_sweep(TINY, {"materials[0].density": [900.0], "materials[1].density": [1100.0, 1200.0]})
    assert [n for n, _ in plan.runs] == [
        "materials.0.density=900.0,materials.1.density=1100.0",
        "materials.0.density=900.0,materials.1.density=1200.0",
    ]
    # values that differ only in case or in unsafe characters still get folders of their own
    # (a free-text key: a scene's name may not hold a / since it names a folder itself)
    plan = plan_sweep(TINY, {"description": ["A", "a", "b/c", "b:c"]})
    names = [n for n, _ in plan.runs]
    assert names == ["description=A", "description=a~2", "description=b_c", "description=b_c~2"]


def test_without_ray_the_ray_option_says_how_to_install(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(AbmpmError, match="^--ray needs ray: pip install 'abmpm\\[sweep\\]'$"):
        import_ray()
    code = main(["sweep", "dam_break", "--set", "simulation.dx=0.1", "--ray", "auto", "--out", str(tmp_path / "s")])
    assert code == 2
    assert capsys.readouterr().err.strip() == f"error: {RAY_MISSING}"
    assert not (tmp_path / "s").exists()


# --------------------------------------------------------------------------- local sweep


@pytest.fixture(scope="module")
def local_sweep(tmp_path_factory):
    """The 2x2 sweep run one after another in this process, one thread per run."""
    out = tmp_path_factory.mktemp("sweep") / "local"
    rows = run_sweep(TINY, VALUES, out, frames=2, threads=1, preview=False)
    return out, rows


def test_local_sweep_writes_a_folder_per_run_and_the_tables(local_sweep):
    out, rows = local_sweep
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == sorted(NAMES)
    for name in NAMES:
        summary = json.loads((out / name / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["frames"] == 2
        assert (out / name / "frames" / "frame_00002.ply").is_file()
    assert [r["run"] for r in rows] == NAMES
    assert all(r["status"] == "completed" and r["message"] is None for r in rows)

    with open(out / "sweep.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["run"] for r in table] == NAMES
    header = list(table[0])
    assert header[:5] == ["run", "simulation.dx", "simulation.refinement.mode", "status", "message"]
    for col in ("particle_count", "particle_count_per_level.0", "steps", "wall_seconds", "steps_per_second",
                "final.kinetic_energy", "final.total_mass", "mode", "device"):
        assert col in header, col
    assert [r["simulation.dx"] for r in table] == ["0.04", "0.04", "0.03", "0.03"]
    assert [r["mode"] for r in table] == ["original", "adaptive", "original", "adaptive"]

    doc = json.loads((out / "sweep.json").read_text())
    assert doc["set"] == VALUES and doc["frames"] == 2 and doc["columns"] == header
    assert len(doc["rows"]) == 4
    for row, csv_row in zip(doc["rows"], table):
        assert isinstance(row["simulation.dx"], float) and isinstance(row["particle_count"], int)
        assert str(row["particle_count"]) == csv_row["particle_count"]
    # the values differ as set: a finer dx makes more particles, the mode is the one asked for
    counts = [r["particle_count"] for r in doc["rows"]]
    assert counts[0] == counts[1] < counts[2] == counts[3]
    assert counts[0] > 1000 and counts[2] > 3000
    assert [r["mode"] for r in doc["rows"]] == [r["simulation.refinement.mode"] for r in doc["rows"]]


def test_run_one_returns_the_row_of_its_summary(tmp_path):
    row = run_one(TINY, {"simulation.dx": 0.08}, tmp_path / "one", frames=1, threads=1, preview=False)
    summary = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert row["run"] == "one" and row["simulation.dx"] == 0.08 and row["status"] == "completed"
    assert row["particle_count"] == summary["particle_count"] and row["steps"] == summary["steps"]
    assert row["final.kinetic_energy"] == summary["series"]["kinetic_energy"][-1]


def test_a_blow_up_is_recorded_and_the_sweep_goes_on(tmp_path, monkeypatch, capsys, poison_velocity):
    """Through the CLI: a scene file, one of two runs blows up: exit 2, both rows."""
    original = Simulation.advance

    def advance(self, seconds=None, frames=None, callback=None):
        def poisoned(sim):
            if callback is not None:
                callback(sim)
            if sim.scene.simulation.dx == 0.08 and sim.frame == 1:
                poison_velocity(sim)

        return original(self, seconds=seconds, frames=frames, callback=poisoned)

    monkeypatch.setattr(Simulation, "advance", advance)
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_TOML)
    out = tmp_path / "wedge"
    code = main(["sweep", str(scene), "--set", "simulation.dx=0.1,0.08", "--frames", "2", "--out", str(out),
                 "--threads", "1"])
    captured = capsys.readouterr()
    assert code == 2
    assert "Traceback" not in captured.err
    assert "[1/2] dx=0.1: completed" in captured.err and "[2/2] dx=0.08: blew_up" in captured.err
    assert captured.err.rstrip().endswith(f"error: 1 of 2 runs failed (1 blew_up); see {out / 'sweep.csv'}")
    assert "dx=0.08" in captured.out and "blew_up" in captured.out  # the table
    rows = json.loads((out / "sweep.json").read_text())["rows"]
    assert [(r["run"], r["status"]) for r in rows] == [("dx=0.1", "completed"), ("dx=0.08", "blew_up")]
    assert "blew up" in rows[1]["message"] and rows[1]["frames"] == 1  # its summary's figures
    assert json.loads((out / "dx=0.08" / "summary.json").read_text())["status"] == "blew_up"


def test_cli_sweep_all_completed_exits_0(tmp_path, capsys):
    scene = tmp_path / "tiny.toml"
    scene.write_text(TINY_TOML)
    out = tmp_path / "wedge"
    code = main(["sweep", str(scene), "--set", "materials[0].viscosity=0,0.01", "--frames", "1",
                 "--out", str(out), "--threads", "1"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "viscosity=0.01" in captured.out and "completed" in captured.out
    with open(out / "sweep.csv", newline="") as f:
        assert [r["materials[0].viscosity"] for r in csv.DictReader(f)] == ["0", "0.01"]


def test_cli_bad_key_names_it(tmp_path, capsys):
    code = main(["sweep", "dam_break", "--set", "simulation.refinement.moed=adaptive", "--out", str(tmp_path / "s")])
    assert code == 2
    assert capsys.readouterr().err.strip() == (
        "error: --set simulation.refinement.moed=adaptive: simulation.refinement.moed: unknown key"
    )
    assert not (tmp_path / "s").exists()


# --------------------------------------------------------------------------- Ray


class _FakeRay:
    """Enough of the ray module to see what a sweep asks of it: tasks are recorded and
    answered with a canned row, in reverse order of submission."""

    def __init__(self, gpus=0):
        self.gpus, self.tasks = gpus, []

    def is_initialized(self):
        return True

    def cluster_resources(self):
        return {"CPU": 8.0, "GPU": float(self.gpus)}

    def remote(self, fn):
        fake = self

        class Remote:
            def options(self, **opts):
                class Bound:
                    def remote(self, *args, **kwargs):
                        fake.tasks.append((fn.__name__, opts, args, kwargs))
                        return len(fake.tasks) - 1

                return Bound()

        return Remote()

    def wait(self, refs, num_returns=1):
        return [max(refs)], [r for r in refs if r != max(refs)]

    def get(self, ref):
        _, opts, args, kwargs = self.tasks[ref]
        if kwargs["name"].endswith("original"):
            raise RuntimeError("worker died")
        return {"run": kwargs["name"], **args[1], "status": "completed", "message": None, "device": kwargs["device"]}


@pytest.mark.parametrize(
    "device, threads, gpus, want",
    [
        ("cpu", None, 0, ({"num_cpus": 1, "num_gpus": 0}, "cpu", 1)),
        (None, 3, 0, ({"num_cpus": 3, "num_gpus": 0}, "cpu", 3)),
        (None, 3, 2, ({"num_cpus": 1, "num_gpus": 1}, "cuda", None)),  # a GPU in the cluster: CUDA
        ("cuda:1", None, 1, ({"num_cpus": 1, "num_gpus": 1}, "cuda", None)),  # Ray's GPU is cuda:0 in the task
    ],
)
def test_ray_tasks_ask_for_threads_cpus_or_one_gpu(tmp_path, monkeypatch, device, threads, gpus, want):
    fake = _FakeRay(gpus)
    monkeypatch.setitem(sys.modules, "ray", fake)
    rows = run_sweep(TINY, VALUES, tmp_path / "s", frames=1, device=device, threads=threads, ray="auto")
    resources, task_device, task_threads = want
    assert len(fake.tasks) == 4
    for fn, opts, args, kwargs in fake.tasks:
        assert fn == "_ray_run_one" and {k: opts[k] for k in resources} == resources
        assert kwargs["device"] == task_device and kwargs["threads"] == task_threads
        assert os.path.isabs(args[2]) and kwargs["frames"] == 1
    # rows come back in the order of the combinations; a task that died is an error row
    assert [r["run"] for r in rows] == NAMES
    assert [r["status"] for r in rows] == ["error", "completed"] * 2
    assert rows[0]["message"] == "Ray task failed: RuntimeError: worker died"
    assert rows[0]["simulation.dx"] == 0.04 and rows[0]["simulation.refinement.mode"] == "original"


def test_an_address_where_no_cluster_answers_is_refused_at_once(tmp_path):
    pytest.importorskip("ray")
    t0 = time.perf_counter()
    with pytest.raises(AbmpmError, match=r"^--ray 127.0.0.1:1: no Ray cluster answers at 127.0.0.1:1; "
                                         r"is a cluster running there\? \(start one with `ray start --head`\)$"):
        run_sweep(TINY, {"simulation.dx": [0.1]}, tmp_path / "s", frames=1, ray="127.0.0.1:1")
    assert time.perf_counter() - t0 < 10  # Ray alone would retry for minutes
    assert not (tmp_path / "s").exists()


@pytest.fixture
def local_ray(monkeypatch):
    """A Ray instance of this test's own (address="local": never a cluster found on the
    machine or in $RAY_ADDRESS; its ports and session folder are Ray's pick), 2 CPUs,
    ABMPM_THREADS=1 in its workers; shut down however the test ends."""
    ray = pytest.importorskip("ray")
    # the workers of a local instance inherit this environment (a job-level
    # runtime_env would do the same but costs ~5 s of set-up here)
    monkeypatch.setenv("ABMPM_THREADS", "1")
    saved = {k: os.environ.get(k) for k in ("RAY_AUTH_MODE",)}  # ray.init sets it in this process
    t0 = time.perf_counter()
    ray.init(
        address="local", num_cpus=2, num_gpus=0, include_dashboard=False, log_to_driver=False,
        object_store_memory=100 * 2**20,
    )
    try:
        yield ray, time.perf_counter() - t0
    finally:
        ray.shutdown()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.mark.slow
def test_ray_sweep_matches_the_local_one(local_sweep, local_ray, tmp_path, monkeypatch):
    ray, startup = local_ray
    out_local, local_rows = local_sweep
    assert all(r["status"] == "completed" for r in local_rows), [r["message"] for r in local_rows]

    def not_here(*args, **kwargs):
        raise AssertionError("run_one ran in the driver, not in a Ray worker")

    # the workers import abmpm.sweep afresh; only a run in this process would hit this
    monkeypatch.setattr("abmpm.sweep.execute.run_one", not_here)
    out = tmp_path / "ray"
    done = []
    t0 = time.perf_counter()
    rows = run_sweep(TINY, VALUES, out, frames=2, threads=1, preview=False, ray="auto",
                     on_done=lambda i, n, row: done.append(row["run"]))
    took = time.perf_counter() - t0
    print(f"ray start-up {startup:.1f} s, sweep {took:.1f} s")
    assert ray.is_initialized()  # run_sweep used this connection and left it open
    assert sorted(done) == sorted(NAMES)
    assert [r["run"] for r in rows] == NAMES  # in the order of the combinations
    assert all(r["status"] == "completed" for r in rows), [r["message"] for r in rows]
    for mine, theirs in zip(rows, local_rows):
        for key in ("simulation.dx", "simulation.refinement.mode", "particle_count", "steps", "frames", "mode"):
            assert mine[key] == theirs[key], key
        # one thread per run is deterministic: the same bytes in every frame and checkpoint
        for sub in ("frames", "checkpoints"):
            files = sorted(p.name for p in (out_local / mine["run"] / sub).iterdir())
            assert files == sorted(p.name for p in (out / mine["run"] / sub).iterdir())
            for f in files:
                a = (out_local / mine["run"] / sub / f).read_bytes()
                assert a == (out / mine["run"] / sub / f).read_bytes(), f"{mine['run']}/{sub}/{f}"
    doc = json.loads((out / "sweep.json").read_text())
    assert doc["ray"] == "auto" and len(doc["rows"]) == 4
