"""A corpus of malformed scenes, meshes and command lines.

Every user mistake must end ``abmpm run`` with exit status 2 and exactly one line on
stderr that names the file and the key (or the mesh file), never a traceback and
never a warning. The scenes are tiny and nearly all of them fail while loading or in
the checks made before anything is allocated, so the whole corpus runs in seconds:
nothing here steps a simulation.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from pathlib import Path

import pytest

from abmpm import cli
from abmpm.cli import main
from abmpm.scene import checks

# A valid scene with every key the cases below change written out once (so that a
# case is a plain text replacement), one frame long.
GOOD = """\
name = "tiny"

[simulation]
domain_min = [0.0, 0.0, 0.0]
domain_max = [0.4, 0.4, 0.4]
dx = 0.05
gravity = [0.0, -9.81, 0.0]
duration = 0.0333
fps = 30.0
cfl = 0.4
max_dt = 0.001
seed = 0
cpic = true

[simulation.walls]
type = "separate"
friction = 0.0

[simulation.refinement]
mode = "original"
threshold = 1.5
bandwidth = 1.0
halo = 1
boxes = []

[[materials]]
name = "water"
model = "fluid"
density = 1000.0
bulk_modulus = 2.0e5
gamma = 7.0
viscosity = 0.0

[[materials]]
name = "jelly"
model = "elastic"
density = 1100.0
youngs_modulus = 1.0e4
poisson_ratio = 0.3

[[bodies]]
shape = "box"
material = "water"
min = [0.05, 0.0, 0.05]
max = [0.2, 0.15, 0.2]
velocity = [0.0, 0.0, 0.0]
angular_velocity = [0.0, 0.0, 0.0]
particles_per_cell = 8

[[bodies]]
shape = "sphere"
material = "jelly"
center = [0.3, 0.25, 0.3]
radius = 0.06

[output]
frames = true
frame_every = 1
checkpoint_every = 10
"""

SHEET = """
[[colliders]]
shape = "sheet"
size = [0.3, 0.3]
center = [0.2, 0.3, 0.2]
rotation = [0.0, 0.0, 0.0]
friction = 0.1
separation = 0.0
refine = true
"""

MOTION = SHEET + """
[colliders.motion]
velocity = [0.0, 0.0, 0.0]
angular_velocity = [0.0, 0.0, 0.0]
pivot = [0.2, 0.3, 0.2]
"""

KEYFRAMES = SHEET + """
[[colliders.motion.keyframes]]
time = 0.0
translation = [0.0, 0.0, 0.0]
rotation = [0.0, 0.0, 0.0]

[[colliders.motion.keyframes]]
time = 0.5
translation = [0.0, -0.1, 0.0]
"""

MESH_BODY = """
[[bodies]]
shape = "mesh"
material = "jelly"
file = "meshes/{name}"
scale = 1.0
translation = [0.0, 0.0, 0.0]
"""

MESH_COLLIDER = """
[[colliders]]
shape = "mesh"
file = "meshes/{name}"
scale = 1.0
"""

LETTERS = """
[[colliders]]
shape = "letter_panel"
center = [0.2, 0.3, 0.2]
size = [0.3, 0.15]
text = "AB"
"""

# a closed tetrahedron in the domain, clear of the other bodies, and broken variants
TETRA = "v 0.25 0.02 0.02\nv 0.38 0.02 0.02\nv 0.25 0.15 0.02\nv 0.25 0.02 0.15\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
MESH_FILES = {
    "tetra.obj": TETRA.encode(),
    "nan.obj": TETRA.replace("v 0.25 0.02 0.15", "v 0.25 nan 0.15").encode(),
    "inf.obj": TETRA.replace("v 0.38 0.02 0.02", "v inf 0.02 0.02").encode(),
    "huge.obj": TETRA.replace("v 0.38 0.02 0.02", "v 1e39 0.02 0.02").encode(),
    "open.obj": TETRA.replace("f 2 3 4\n", "").encode(),
    "badface.obj": TETRA.replace("f 2 3 4", "f 2 3 9").encode(),
    "points.obj": TETRA.split("f")[0].encode(),
    "garbage.obj": bytes(range(256)) * 8,
    "garbage.stl": bytes(range(255, -1, -1)) * 9,
    "garbage.ply": b"\x00\x01\x02 not a ply file \xff" * 40,
    "empty.obj": b"",
    "empty.stl": b"",
    "latin1.obj": "# caf\xe9\n".encode("latin-1") + b"\x00\x80" + TETRA.encode(),
    "mesh.txt": TETRA.encode(),
}


def sub(*pairs: str, extra: str = "") -> str:
    """GOOD with each (old, new) replaced (old must occur exactly once), plus ``extra``."""
    text = GOOD + extra
    for old, new in zip(pairs[::2], pairs[1::2]):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    return text


def col(*pairs: str, base: str = SHEET) -> str:
    """GOOD plus a collider (``base``) with replacements in the collider's text."""
    for old, new in zip(pairs[::2], pairs[1::2]):
        assert base.count(old) == 1, old
        base = base.replace(old, new)
    return GOOD + base


def mesh_body(name: str, *pairs: str) -> str:
    body = MESH_BODY.format(name=name)
    for old, new in zip(pairs[::2], pairs[1::2]):
        body = body.replace(old, new)
    return GOOD + body


# name -> (scene text, substrings of the one error line). The line must also start
# with "error: " and name scene.toml or, for a mesh, the mesh file.
CASES: dict[str, tuple[str, tuple[str, ...]]] = {
    # ---- non-finite numbers, one key each (TOML spells them inf, +inf, -inf, nan)
    "inf_youngs_modulus": (sub("youngs_modulus = 1.0e4", "youngs_modulus = inf"),
                           ("materials[1].youngs_modulus", "finite")),
    "nan_density": (sub("density = 1000.0", "density = nan"), ("materials[0].density", "finite")),
    "neg_inf_density": (sub("density = 1100.0", "density = -inf"), ("materials[1].density", "finite")),
    "inf_bulk_modulus": (sub("bulk_modulus = 2.0e5", "bulk_modulus = +inf"), ("materials[0].bulk_modulus",)),
    "nan_viscosity": (sub("viscosity = 0.0", "viscosity = nan"), ("materials[0].viscosity", "finite")),
    "nan_gamma": (sub("gamma = 7.0", "gamma = nan"), ("materials[0].gamma", "finite")),
    "nan_poisson_ratio": (sub("poisson_ratio = 0.3", "poisson_ratio = nan"), ("materials[1].poisson_ratio",)),
    "inf_fps": (sub("fps = 30.0", "fps = inf"), ("simulation.fps", "finite")),
    "nan_duration": (sub("duration = 0.0333", "duration = nan"), ("simulation.duration", "finite")),
    "inf_dx": (sub("dx = 0.05", "dx = inf"), ("simulation.dx", "finite")),
    "inf_gravity": (sub("gravity = [0.0, -9.81, 0.0]", "gravity = [0.0, -inf, 0.0]"),
                    ("simulation.gravity[1]", "finite")),
    "nan_domain_max": (sub("domain_max = [0.4, 0.4, 0.4]", "domain_max = [0.4, nan, 0.4]"),
                       ("simulation.domain_max[1]",)),
    "inf_domain_min": (sub("domain_min = [0.0, 0.0, 0.0]", "domain_min = [-inf, 0.0, 0.0]"),
                       ("simulation.domain_min[0]",)),
    "nan_cfl": (sub("cfl = 0.4", "cfl = nan"), ("simulation.cfl", "finite")),
    "inf_max_dt": (sub("max_dt = 0.001", "max_dt = inf"), ("simulation.max_dt", "finite")),
    "nan_box_min": (sub("min = [0.05, 0.0, 0.05]", "min = [nan, 0.0, 0.05]"), ("bodies[0].min[0]",)),
    "inf_body_velocity": (sub("velocity = [0.0, 0.0, 0.0]\nangular", "velocity = [inf, 0.0, 0.0]\nangular"),
                          ("bodies[0].velocity[0]", "finite")),
    "nan_angular_velocity": (sub("angular_velocity = [0.0, 0.0, 0.0]", "angular_velocity = [0.0, nan, 0.0]"),
                             ("bodies[0].angular_velocity[1]",)),
    "nan_sphere_center": (sub("center = [0.3, 0.25, 0.3]", "center = [0.3, nan, 0.3]"), ("bodies[1].center[1]",)),
    "inf_sphere_radius": (sub("radius = 0.06", "radius = inf"), ("bodies[1].radius", "finite")),
    "inf_mesh_scale": (mesh_body("tetra.obj", "scale = 1.0", "scale = inf"), ("bodies[2].scale", "finite")),
    "nan_mesh_scale_vector": (mesh_body("tetra.obj", "scale = 1.0", "scale = [1.0, nan, 1.0]"),
                              ("bodies[2].scale", "finite")),
    "nan_mesh_translation": (mesh_body("tetra.obj", "translation = [0.0, 0.0, 0.0]", "translation = [0.0, 0.0, nan]"),
                             ("bodies[2].translation[2]",)),
    "inf_bunny_size": (GOOD + '\n[[bodies]]\nshape = "bunny"\nmaterial = "jelly"\ncenter = [0.2, 0.3, 0.2]\n'
                       "size = inf\n", ("bodies[2].size", "finite")),
    "nan_collider_center": (col("center = [0.2, 0.3, 0.2]", "center = [nan, 0.3, 0.2]"), ("colliders[0].center[0]",)),
    "inf_collider_rotation": (col("rotation = [0.0, 0.0, 0.0]", "rotation = [0.0, inf, 0.0]"),
                              ("colliders[0].rotation[1]",)),
    "nan_collider_friction": (col("friction = 0.1", "friction = nan"), ("colliders[0].friction", "finite")),
    "inf_collider_separation": (col("separation = 0.0", "separation = inf"), ("colliders[0].separation",)),
    "inf_collider_size": (col("size = [0.3, 0.3]", "size = [inf, 0.3]"), ("colliders[0].size[0]",)),
    "nan_motion_velocity": (col("\nvelocity = [0.0, 0.0, 0.0]", "\nvelocity = [nan, 0.0, 0.0]", base=MOTION),
                            ("colliders[0].motion.velocity[0]",)),
    "inf_motion_angular_velocity": (
        col("angular_velocity = [0.0, 0.0, 0.0]", "angular_velocity = [0.0, inf, 0.0]", base=MOTION),
        ("colliders[0].motion.angular_velocity[1]",)),
    "nan_motion_pivot": (col("pivot = [0.2, 0.3, 0.2]", "pivot = [0.2, nan, 0.2]", base=MOTION),
                         ("colliders[0].motion.pivot[1]",)),
    "inf_keyframe_time": (col("time = 0.5", "time = inf", base=KEYFRAMES),
                          ("colliders[0].motion.keyframes[1].time", "finite")),
    "nan_keyframe_translation": (col("translation = [0.0, -0.1, 0.0]", "translation = [0.0, nan, 0.0]",
                                     base=KEYFRAMES), ("colliders[0].motion.keyframes[1].translation[1]",)),
    "inf_keyframe_rotation": (col("rotation = [0.0, 0.0, 0.0]\n\n[[", "rotation = [inf, 0.0, 0.0]\n\n[[",
                                  base=KEYFRAMES), ("colliders[0].motion.keyframes[0].rotation[0]",)),
    "nan_refinement_box": (sub("boxes = []", "boxes = [[[0.0, 0.0, 0.0], [0.2, nan, 0.2]]]"),
                           ("simulation.refinement.boxes[0][1][1]",)),
    "inf_refinement_threshold": (sub("threshold = 1.5", "threshold = inf"), ("simulation.refinement.threshold",)),
    "nan_refinement_bandwidth": (sub("bandwidth = 1.0", "bandwidth = nan"), ("simulation.refinement.bandwidth",)),
    "inf_wall_friction": (sub("friction = 0.0\n\n[simulation.refinement]", "friction = inf\n\n[simulation.refinement]"),
                          ("simulation.walls.friction", "finite")),
    "nan_wall_face_friction": (sub('type = "separate"\n', 'type = "separate"\ny_min = { friction = nan }\n'),
                               ("simulation.walls.y_min.friction",)),
    "inf_mesh_collider_scale": (GOOD + MESH_COLLIDER.format(name="tetra.obj").replace("scale = 1.0", "scale = inf"),
                                ("colliders[0].scale", "finite")),
    "nan_sand_friction_angle": (sub('model = "elastic"', 'model = "sand"\nfriction_angle = nan'),
                                ("materials[1].friction_angle",)),
    "inf_snow_hardening": (sub('model = "elastic"', 'model = "snow"\nhardening = inf'), ("materials[1].hardening",)),
    # ---- strings and other wrong types are not coerced
    "string_dx": (sub("dx = 0.05", 'dx = "0.05"'), ("simulation.dx", "expected a number, got '0.05'")),
    "string_cpic": (sub("cpic = true", 'cpic = "yes"'), ("simulation.cpic", "expected true or false, got 'yes'")),
    "int_cpic": (sub("cpic = true", "cpic = 1"), ("simulation.cpic", "expected true or false, got 1")),
    "string_youngs_modulus": (sub("youngs_modulus = 1.0e4", 'youngs_modulus = "1e4"'),
                              ("materials[1].youngs_modulus", "expected a number")),
    "string_in_vector": (sub("gravity = [0.0, -9.81, 0.0]", 'gravity = [0.0, "-9.81", 0.0]'),
                         ("simulation.gravity[1]", "expected a number")),
    "bool_for_number": (sub("fps = 30.0", "fps = true"), ("simulation.fps", "expected a number, got true")),
    "string_output_flag": (sub("frames = true", 'frames = "true"'), ("output.frames", "expected true or false")),
    "float_seed": (sub("seed = 0", "seed = 1.5"), ("simulation.seed", "expected an integer")),
    "float_particles_per_cell": (sub("particles_per_cell = 8", "particles_per_cell = 8.0"),
                                 ("bodies[0].particles_per_cell", "expected an integer")),
    "string_collider_refine": (col("refine = true", 'refine = "no"'), ("colliders[0].refine", "true or false")),
    "number_for_name": (sub('name = "tiny"', "name = 3"), ("name", "expected a string")),
    "number_for_material_reference": (sub('material = "water"', "material = 1"), ("bodies[0].material",)),
    "table_for_number": (sub("dx = 0.05", "dx = { value = 0.05 }"), ("simulation.dx", "expected a number")),
    # ---- zero, negative and out-of-range values
    "zero_fps": (sub("fps = 30.0", "fps = 0"), ("simulation.fps", "must be > 0")),
    "negative_duration": (sub("duration = 0.0333", "duration = -1"), ("simulation.duration", "must be > 0")),
    "zero_radius": (sub("radius = 0.06", "radius = 0"), ("bodies[1].radius", "must be > 0")),
    "zero_density": (sub("density = 1000.0", "density = 0"), ("materials[0].density", "must be > 0")),
    "cfl_above_one": (sub("cfl = 0.4", "cfl = 1.5"), ("simulation.cfl", "must be <= 1")),
    "negative_seed": (sub("seed = 0", "seed = -1"), ("simulation.seed", "must be >= 0")),
    "particles_per_cell_not_cube": (sub("particles_per_cell = 8", "particles_per_cell = 7"),
                                    ("bodies[0].particles_per_cell", "cube number")),
    "negative_collider_size": (col("size = [0.3, 0.3]", "size = [0.3, -0.3]"), ("colliders[0].size[1]", "> 0")),
    "inverted_refinement_box": (sub("boxes = []", "boxes = [[[0.3, 0.3, 0.3], [0.1, 0.1, 0.1]]]"),
                                ("simulation.refinement.boxes", "min must not exceed max")),
    "refinement_box_outside_the_domain": (sub("boxes = []", "boxes = [[[0.5, 0.1, 0.1], [0.9, 0.3, 0.3]]]"),
                                          ("simulation.refinement.boxes[0]", "outside the domain on axis x")),
    # a box thinner than a cell between two centres refined nothing without a word (until 2026-11-27)
    "refinement_box_between_cell_centres": (sub("boxes = []", "boxes = [[[0.0, 0.11, 0.0], [0.2, 0.12, 0.2]]]"),
                                            ("simulation.refinement.boxes[0]", "no cell centre on axis y")),
    "refinement_box_with_no_volume": (sub("boxes = []", "boxes = [[[0.1, 0.1, 0.1], [0.1, 0.1, 0.1]]]"),
                                      ("simulation.refinement.boxes[0]", "would refine nothing")),
    "refinement_box_one_corner": (sub("boxes = []", "boxes = [[0.1, 0.1, 0.1]]"),
                                  ("simulation.refinement.boxes[0]", "two corners")),
    "refinement_box_three_corners": (sub("boxes = []", "boxes = [[[0.0, 0.0, 0.0], [0.2, 0.2, 0.2], [0.3, 0.3, 0.3]]]"),
                                     ("simulation.refinement.boxes[0]", "two corners")),
    # explicit viscosity's step limit (dx^2 rho / eta) past 1e8 steps a frame
    "absurd_viscosity": (sub("viscosity = 0.0", "viscosity = 1.0e15"), ("materials[0].viscosity", "sets the time step")),
    # gamma = 1e5 hung (J^-gamma by gamma multiplications per particle and step)
    "absurd_gamma": (sub("gamma = 7.0", "gamma = 1.0e5"), ("materials[0].gamma", "100")),
    "inverted_domain": (sub("domain_max = [0.4, 0.4, 0.4]", "domain_max = [0.4, -0.4, 0.4]"),
                        ("simulation.domain_max", "must exceed domain_min")),
    # ---- numbers too big (or too small) for the solver, or that break time stepping
    "huge_youngs_modulus": (sub("youngs_modulus = 1.0e4", "youngs_modulus = 1e39"),
                            ("materials[1].youngs_modulus", "single-precision")),
    "huge_density": (sub("density = 1000.0", "density = 1e308"), ("materials[0].density", "single-precision")),
    "denormal_dx": (sub("dx = 0.05", "dx = 1e-300"), ("simulation.dx", "single-precision")),
    "huge_fps": (sub("fps = 30.0", "fps = 1e30"), ("simulation.fps", "frames")),
    "million_frames": (sub("fps = 30.0", "fps = 1e8"), ("simulation.fps", "frames", "1e+06")),
    "huge_bandwidth": (sub("bandwidth = 1.0", "bandwidth = 1e6"), ("simulation.refinement.bandwidth", "16")),
    "huge_duration": (sub("duration = 0.0333", "duration = 1e30"), ("simulation.duration", "frames")),
    "tiny_max_dt": (sub("max_dt = 0.001", "max_dt = 1e-30"), ("simulation.max_dt", "time steps")),
    "tiny_cfl": (sub("cfl = 0.4", "cfl = 1e-30"), ("simulation.cfl", "time steps")),
    "huge_body_velocity": (sub("velocity = [0.0, 0.0, 0.0]\nangular", "velocity = [3e38, 3e38, 0.0]\nangular"),
                           ("bodies[0].velocity", "time steps")),
    "huge_angular_velocity": (sub("angular_velocity = [0.0, 0.0, 0.0]", "angular_velocity = [0.0, 1e38, 0.0]"),
                              ("bodies[0].angular_velocity", "time steps")),
    # 1e6 m/s: steppable within the frame limit, but its first step is under the fraction
    # of the step at rest where a run stops as blown up: refused before the run
    "body_velocity_beyond_the_blow_up_limit": (
        sub("velocity = [0.0, 0.0, 0.0]\nangular", "velocity = [1e6, 0.0, 0.0]\nangular"),
        ("bodies[0].velocity", "step at rest")),
    "huge_bulk_modulus": (sub("bulk_modulus = 2.0e5", "bulk_modulus = 3e38"),
                          ("materials[0].bulk_modulus", "wave speed")),
    "tiny_density": (sub("density = 1000.0", "density = 1e-30"), ("materials[0].density", "wave speed")),
    "snow_hardening_overflow": (sub('model = "elastic"', 'model = "snow"\nhardening = 1e30'),
                                ("materials[1].hardening", "wave speed")),
    "domain_far_from_origin": (sub("domain_min = [0.0, 0.0, 0.0]", "domain_min = [-1e9, 0.0, 0.0]"),
                               ("simulation.domain_min", "single precision")),
    "huge_keyframe_time": (col("time = 0.5", "time = 1e39", base=KEYFRAMES),
                           ("colliders[0].motion.keyframes[1].time", "single-precision")),
    "collider_far_away": (col("center = [0.2, 0.3, 0.2]", "center = [3e20, 0.3, 0.2]"), ("colliders[0]", "origin")),
    "collider_absurd_size": (col("size = [0.3, 0.3]", "size = [3e38, 3e38]"), ("colliders[0]", "size")),
    "huge_mesh_scale": (mesh_body("tetra.obj", "scale = 1.0", "scale = 3e38"), ("bodies[2].scale",)),
    # ---- unknown keys
    "unknown_top_level_key": (sub('name = "tiny"', 'name = "tiny"\ncolour = "red"'), ("colour: unknown key",)),
    "unknown_wall_key": (sub('type = "separate"\n', 'type = "separate"\nfrition = 0.2\n'),
                         ("simulation.walls.frition: unknown key",)),
    "unknown_refinement_key": (sub("halo = 1", "halo = 1\nfactr = 2"), ("simulation.refinement.factr: unknown key",)),
    "unknown_motion_key": (col("pivot = [0.2, 0.3, 0.2]", "speed = 2.0", base=MOTION),
                           ("colliders[0].motion.speed: unknown key",)),
    "unknown_keyframe_key": (col("time = 0.5", "time = 0.5\nscale = 2.0", base=KEYFRAMES),
                             ("colliders[0].motion.keyframes[1].scale: unknown key",)),
    "unknown_output_key": (sub("frame_every = 1", "frame_every = 1\nformat = 'vtk'"), ("output.format: unknown key",)),
    # ---- letter panel text
    "empty_letter_text": (col('text = "AB"', 'text = ""', base=LETTERS), ("colliders[0].text", "must not be empty")),
    "blank_letter_text": (col('text = "AB"', 'text = "   "', base=LETTERS), ("colliders[0].text", "visible")),
    "whitespace_letter_text": (col('text = "AB"', 'text = "\\t\\n"', base=LETTERS), ("colliders[0].text", "visible")),
    "invisible_letter_text": (col('text = "AB"', 'text = "\\u200b"', base=LETTERS),
                              ("colliders[0].text", "no visible glyphs")),
    "control_character_in_letter_text": (col('text = "AB"', 'text = "A\\u0007B"', base=LETTERS),
                                         ("colliders[0].text", "U+0007", "control")),
    # ---- missing and broken files
    "missing_mesh_body_file": (mesh_body("missing.obj"), ("missing.obj", "not found", "bodies[2].file")),
    "missing_mesh_collider_file": (GOOD + MESH_COLLIDER.format(name="missing.stl"),
                                   ("missing.stl", "not found", "colliders[0].file")),
    "nan_vertex_mesh_body": (mesh_body("nan.obj"), ("nan.obj", "non-finite", "bodies[2].file")),
    "inf_vertex_mesh_collider": (GOOD + MESH_COLLIDER.format(name="inf.obj"),
                                 ("inf.obj", "non-finite", "colliders[0].file")),
    "huge_vertex_mesh": (mesh_body("huge.obj"), ("huge.obj", "coordinates", "bodies[2].file")),
    "garbage_obj": (mesh_body("garbage.obj"), ("garbage.obj", "not a valid OBJ file", "bodies[2].file")),
    "garbage_stl_collider": (GOOD + MESH_COLLIDER.format(name="garbage.stl"),
                             ("garbage.stl", "not a valid STL file", "colliders[0].file")),
    "garbage_ply": (mesh_body("garbage.ply"), ("garbage.ply", "not a valid PLY file", "bodies[2].file")),
    "non_utf8_obj": (mesh_body("latin1.obj"), ("latin1.obj", "bodies[2].file")),
    "empty_obj": (mesh_body("empty.obj"), ("empty.obj", "empty", "bodies[2].file")),
    "empty_stl_collider": (GOOD + MESH_COLLIDER.format(name="empty.stl"), ("empty.stl", "empty", "colliders[0].file")),
    "directory_as_mesh": (mesh_body("folder.obj"), ("folder.obj", "is not a file", "bodies[2].file")),
    "wrong_mesh_extension": (mesh_body("mesh.txt"), ("mesh.txt", "unsupported mesh format", "bodies[2].file")),
    "open_mesh_as_solid": (mesh_body("open.obj"), ("open.obj", "not closed", "bodies[2].file")),
    "face_index_out_of_range": (mesh_body("badface.obj"), ("badface.obj", "bodies[2].file")),
    "mesh_without_faces": (mesh_body("points.obj"), ("points.obj", "bodies[2].file")),
    "toml_syntax_error": (sub("[simulation.walls]", "[simulation.walls"), ("TOML syntax error",)),
    "scene_not_utf8": (GOOD.replace('name = "tiny"', 'name = "caf\udce9"'), ("not UTF-8",)),
    # the name is the default output folder: never a path out of out/ (a run clears frames there)
    "name_climbs_out": (sub('name = "tiny"', 'name = "../../elsewhere"'), ("name:", "plain folder name")),
    "name_absolute": (sub('name = "tiny"', 'name = "/tmp/elsewhere"'), ("name:", "plain folder name")),
    "name_empty": (sub('name = "tiny"', 'name = ""'), ("name:", "plain folder name")),
    "name_dot": (sub('name = "tiny"', 'name = "."'), ("name:", "plain folder name")),
    "device_unknown": (sub("seed = 0\n", 'seed = 0\ndevice = "tpu"\n'), ("simulation.device", "tpu")),
}

MESH_CASE_FILES = {"folder.obj": None}  # None: a directory


def write_scene(tmp_path: Path, text: str) -> None:
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name, data in MESH_FILES.items():
        (meshes / name).write_bytes(data)
    for name in MESH_CASE_FILES:
        (meshes / name).mkdir()
    (tmp_path / "scene.toml").write_bytes(text.encode("utf-8", "surrogateescape"))


def run_cli(args: list[str], capsys) -> tuple[int, str, list]:
    """Run the CLI in-process; (exit status, stderr, warnings raised meanwhile)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = main(args)
    err = capsys.readouterr().err
    return code, err, [w for w in caught if issubclass(w.category, (RuntimeWarning, UserWarning))]


def assert_one_line_error(code, err, caught, *expected, prefix="error: "):
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(prefix), err
    for e in expected:
        assert e in lines[0], f"{e!r} not in {lines[0]!r}"
    assert not caught, [str(w.message) for w in caught]


RUN = ["run", "scene.toml", "--out", "out", "--no-preview", "-q", "--device", "cpu"]


@pytest.fixture
def in_tmp(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_scene(case, in_tmp, capsys):
    text, expected = CASES[case]
    write_scene(in_tmp, text)
    code, err, caught = run_cli(RUN, capsys)
    assert_one_line_error(code, err, caught, *expected)
    line = err.strip()
    mesh_case = any(e.endswith((".obj", ".stl", ".ply", ".txt")) for e in expected)
    if not mesh_case:
        assert line.startswith("error: scene.toml: "), line
    assert not (in_tmp / "out" / "frames").exists()  # nothing was simulated


def test_the_corpus_is_big_enough():
    assert len(CASES) + len(MEMORY_CASES) + len(ARG_CASES) >= 60


def test_the_good_scene_is_good(in_tmp):
    """The cases are one change away from a scene that loads, passes the checks and
    builds (bodies, meshes, colliders): each case fails for its own reason."""
    from abmpm.geometry.placement import collider_mesh
    from abmpm.scene.loader import load_scene
    from abmpm.simulation import sample_scene

    text = (GOOD + MESH_BODY.format(name="tetra.obj") + KEYFRAMES + MOTION.replace("0.3, 0.2]", "0.35, 0.2]")
            + LETTERS + MESH_COLLIDER.format(name="tetra.obj"))
    write_scene(in_tmp, text)
    scene = load_scene("scene.toml")
    scene.check_feasible(None, "cpu")
    for i, c in enumerate(scene.colliders):
        assert len(collider_mesh(c, scene.resolve, f"colliders[{i}]").faces) > 0
    assert len(sample_scene(scene)["x"]) > 0


# --------------------------------------------------------------------------- memory


GRID_TOO_BIG = sub("dx = 0.05", "dx = 0.0008", "min = [0.05, 0.0, 0.05]", "min = [0.1, 0.1, 0.1]",
                   "max = [0.2, 0.15, 0.2]", "max = [0.11, 0.11, 0.11]",
                   "particles_per_cell = 8", "particles_per_cell = 1", "radius = 0.06", "radius = 0.01")
FINEST_TOO_BIG = sub("dx = 0.05", "dx = 0.004", 'mode = "original"', 'mode = "finest"\nfactor = 4',
                     "max = [0.2, 0.15, 0.2]", "max = [0.11, 0.11, 0.11]", "min = [0.05, 0.0, 0.05]",
                     "min = [0.1, 0.1, 0.1]", "radius = 0.06", "radius = 0.01")
PARTICLES_TOO_MANY = sub("domain_max = [0.4, 0.4, 0.4]", "domain_max = [4.0, 0.4, 4.0]", "dx = 0.05", "dx = 0.01",
                         "max = [0.2, 0.15, 0.2]", "max = [4.0, 0.2, 4.0]", "min = [0.05, 0.0, 0.05]",
                         "min = [0.0, 0.0, 0.0]", "particles_per_cell = 8", "particles_per_cell = 27")
PARTICLES_OVER_INT32 = sub("domain_max = [0.4, 0.4, 0.4]", "domain_max = [10.0, 1.0, 10.0]", "dx = 0.05", "dx = 0.01",
                           "max = [0.2, 0.15, 0.2]", "max = [10.0, 1.0, 10.0]", "min = [0.05, 0.0, 0.05]",
                           "min = [0.0, 0.0, 0.0]", "particles_per_cell = 8", "particles_per_cell = 125")
GRID_OVER_INT32 = sub("dx = 0.05", "dx = 0.00029")

MEMORY_CASES = {
    "dense_grid": (GRID_TOO_BIG, ("simulation.dx", "the grid", "nodes", "GB", "more than the 1.0 GB", "raise dx")),
    "finest_grid": (FINEST_TOO_BIG, ("simulation.dx", "finest grid", "GB", "lower refinement.factor")),
    "too_many_particles": (PARTICLES_TOO_MANY, ("bodies[0]", "particles", "GB", "particles_per_cell")),
    "particles_over_32_bit": (PARTICLES_OVER_INT32, ("bodies[0]", "32-bit")),
    "grid_over_2e9_nodes": (GRID_OVER_INT32, ("simulation.dx", "2e9 nodes")),
}


@pytest.mark.parametrize("case", sorted(MEMORY_CASES))
def test_scene_too_big_for_memory(case, in_tmp, capsys, monkeypatch):
    """Refused before anything is allocated, with the estimate and the key (a machine
    with 1 GB of RAM, so that the outcome does not depend on this machine's)."""
    monkeypatch.setattr(checks, "_ram_bytes", lambda: 10**9)
    text, expected = MEMORY_CASES[case]
    write_scene(in_tmp, text)
    code, err, caught = run_cli(RUN, capsys)
    assert_one_line_error(code, err, caught, "error: scene.toml: ", *expected)
    assert not (in_tmp / "out").exists()  # refused before the output folder was made


def test_memory_estimate_formula():
    from abmpm.scene.loader import scene_from_dict
    import tomllib

    scene = scene_from_dict(tomllib.loads(GRID_TOO_BIG))
    est = checks.memory_estimate(scene)
    cells = round(0.4 / 0.0008)
    assert est["grid_nodes"] == (cells + 7) ** 3
    assert est["grid_bytes"] == est["grid_nodes"] * checks.GRID_NODE_BYTES
    # the box at 1 particle per cell, the sphere's bounding box at 8
    assert est["particles"] == pytest.approx((0.01**3 * 1 + 0.02**3 * 8) / 0.0008**3, rel=1e-6)
    finest = checks.memory_estimate(scene, "finest")
    assert finest["grid_nodes"] == (2 * cells + 7) ** 3  # dx / factor (2)
    assert finest["particles"] == pytest.approx(8 * est["particles"])


def test_memory_check_counts_colliders_color_field():
    from abmpm.scene.loader import scene_from_dict
    import tomllib

    plain = checks.memory_estimate(scene_from_dict(tomllib.loads(GOOD)))
    with_sheet = checks.memory_estimate(scene_from_dict(tomllib.loads(GOOD + SHEET)))
    assert with_sheet["grid_bytes"] == plain["grid_nodes"] * (checks.GRID_NODE_BYTES + checks.COLOR_NODE_BYTES)


# --------------------------------------------------------------------------- command line


ARG_CASES = {
    "no_scene": (["run"], "SCENE"),
    "frames_zero": (["run", "scene.toml", "--frames", "0"], "--frames"),
    "frames_not_a_number": (["run", "scene.toml", "--frames", "ten"], "--frames"),
    "frames_beyond_any_run": (["run", "scene.toml", "--frames", "10000000000000"], "--frames"),
    "unknown_option": (["run", "scene.toml", "--bogus"], "--bogus"),
    "unknown_command": (["simulate", "scene.toml"], "simulate"),
    "bad_mode": (["run", "scene.toml", "--mode", "fine"], "--mode"),
    "no_command": ([], "COMMAND"),
}


@pytest.mark.parametrize("case", sorted(ARG_CASES))
def test_bad_command_line(case, in_tmp, capsys):
    args, expected = ARG_CASES[case]
    write_scene(in_tmp, GOOD)
    code, err, caught = run_cli(args, capsys)
    assert_one_line_error(code, err, caught, expected, prefix="abmpm: error: ")
    assert "usage:" not in err


def test_missing_scene_file(in_tmp, capsys):
    code, err, caught = run_cli(["run", "nothere.toml", "-q"], capsys)
    assert_one_line_error(code, err, caught, "nothere.toml", "not found")


def test_scene_path_is_a_directory(in_tmp, capsys):
    (in_tmp / "folder.toml").mkdir()
    code, err, caught = run_cli(["run", "folder.toml", "-q"], capsys)
    assert_one_line_error(code, err, caught, "folder.toml", "is not a file")


def test_unknown_device(in_tmp, capsys):
    write_scene(in_tmp, GOOD)
    code, err, caught = run_cli(["run", "scene.toml", "-q", "--device", "tpu"], capsys)
    assert_one_line_error(code, err, caught, "tpu")


# --------------------------------------------------------------------------- markup in paths


def test_brackets_in_paths_print_literally(in_tmp, capsys, monkeypatch):
    """A path with [ ] is not rich markup: the banner shows it as it is."""
    monkeypatch.setattr(checks, "_ram_bytes", lambda: 10**9)
    folder = in_tmp / "[red]x[/red]"  # folders "[red]x[" and "red]"
    folder.mkdir(parents=True)
    (folder / "sc[bold]ene.toml").write_text(GRID_TOO_BIG)  # loads, then refused by the memory check
    scene = "[red]x[/red]/sc[bold]ene.toml"
    code, err, caught = run_cli(["run", scene, "--out", "o[/]ut", "--device", "cpu"], capsys)
    assert code == 2, err
    assert "Traceback" not in err and "MarkupError" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[0] == f"abmpm running {scene} -> o[/]ut", lines
    assert lines[-1].startswith(f"error: {scene}: simulation.dx: "), lines
    assert len(lines) == 2


def test_bad_scene_in_bracket_folder(in_tmp, capsys):
    folder = in_tmp / "[bold]"
    folder.mkdir()
    (folder / "scene.toml").write_text(sub("fps = 30.0", "fps = nan"))
    code, err, caught = run_cli(["run", "[bold]/scene.toml", "-q"], capsys)
    assert_one_line_error(code, err, caught, "error: [bold]/scene.toml: simulation.fps")


def test_summary_prints_paths_literally(capsys):
    summary = {"scene": "a[/]b", "particle_count": 3, "frames": 1, "sim_time": 0.03, "steps": 2,
               "steps_per_second": 10.0, "device": "cpu", "wall_seconds": 0.1,
               "outputs": {"summary": "summary.json", "frames": "frames/frame_NNNNN.ply"}}
    cli._print_summary(summary, Path("o[/red]ut"))
    out = capsys.readouterr().out
    assert "a[/]b" in out and "o[/red]ut/summary.json" in out


# --------------------------------------------------------------------------- frame 0, temporaries


def test_non_finite_initial_state_is_refused(in_tmp, capsys, monkeypatch):
    """A state that is NaN at frame 0 is not written as a good frame."""
    import numpy as np

    import abmpm.simulation as simulation

    real = simulation.sample_scene

    def poisoned(scene, *args):
        arrays = real(scene, *args)
        arrays["v"][0] = np.nan
        return arrays

    monkeypatch.setattr(simulation, "sample_scene", poisoned)
    write_scene(in_tmp, GOOD)
    code, err, caught = run_cli(RUN, capsys)
    assert_one_line_error(code, err, caught, "error: scene.toml: bodies[0].velocity", "not finite")
    assert not (in_tmp / "out" / "frames").exists()


def _leftover(folder: Path, name: str) -> Path:
    """A temporary file named the way atomic_write names them, as a crash leaves it."""
    path = folder / name
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + path.suffix, dir=folder)
    os.close(fd)
    return Path(tmp)


def test_a_folder_no_run_wrote_is_not_cleared(in_tmp, capsys):
    """--out naming a folder with files of abmpm's names but no scene.json (not a run's):
    refused before anything is removed."""
    write_scene(in_tmp, GOOD)
    frames = in_tmp / "out" / "frames"
    frames.mkdir(parents=True)
    (frames / "frame_00099.ply").write_text("someone else's")
    (in_tmp / "out" / "summary.json").write_text("{}")
    code, err, caught = run_cli(RUN, capsys)
    assert_one_line_error(code, err, caught, "not an abmpm run folder", "frames/frame_00099.ply")
    assert (frames / "frame_00099.ply").read_text() == "someone else's"


def test_interrupted_writes_are_cleaned_on_the_next_run(in_tmp, capsys):
    out = in_tmp / "out"
    stale = [
        _leftover(out / "frames", "frame_00003.ply"),
        _leftover(out / "colliders", "collider_00003.ply"),
        _leftover(out / "checkpoints", "checkpoint_00010.npz"),
        _leftover(out, "summary.json"),
        _leftover(out, "preview.mp4"),
    ]
    fd, probe = tempfile.mkstemp(prefix=".abmpm-write-test-", dir=out)
    os.close(fd)
    stale.append(Path(probe))
    keep = [out / ".keep", out / "notes.tmp.txt", out / "frames" / ".frame_notes"]
    for p in keep:
        p.write_text("mine")
    # a run that fails after the output folder is prepared (body outside the domain)
    write_scene(in_tmp, sub("max = [0.2, 0.15, 0.2]", "max = [0.2, 0.15, 0.6]"))
    code, err, caught = run_cli(RUN, capsys)
    assert_one_line_error(code, err, caught, "error: scene.toml: bodies[0]", "outside the domain")
    assert [p for p in stale if p.exists()] == []
    assert all(p.exists() for p in keep)


def test_interrupted_writes_are_cleaned_on_resume(in_tmp, capsys):
    out = in_tmp / "out"
    stale = _leftover(out / "checkpoints", "checkpoint_00001.npz")
    write_scene(in_tmp, sub("max = [0.2, 0.15, 0.2]", "max = [0.2, 0.15, 0.6]"))
    code, err, caught = run_cli(RUN + ["--resume"], capsys)
    assert code == 2
    assert not stale.exists()


# --------------------------------------------------------------------------- Python API


def test_python_api_keeps_lists_numpy_and_ints():
    """Strict types for files, but lists, tuples, numpy numbers and ints still work."""
    import numpy as np

    from abmpm.scene.model import BoxBody, Fluid, Refinement, Scene, SimulationSettings

    scene = Scene(
        simulation=SimulationSettings(domain_max=[1, 1, 1], dx=np.float32(0.05), seed=np.int64(2), cpic=np.bool_(True),
                                      refinement=Refinement(boxes=[([0, 0, 0], (1, 1, 1))])),
        materials=[Fluid(name="w", density=1000)],
        bodies=[BoxBody(material="w", min=np.array([0.1, 0.1, 0.1]), max=(0.2, 0.2, 0.2))],
    )
    assert scene.simulation.domain_max == (1.0, 1.0, 1.0) and isinstance(scene.simulation.dx, float)
    assert scene.simulation.seed == 2 and scene.simulation.cpic is True
    assert scene.bodies[0].min == (0.1, 0.1, 0.1)
    again = Scene.model_validate(scene.model_dump(mode="json"))  # resume and render read scene.json
    assert again == scene
    with pytest.raises(ValueError, match="finite"):
        Fluid(name="w", density=float("inf"))
    with pytest.raises(ValueError):
        SimulationSettings(dx="0.05")


# --------------------------------------------------------------------------- the Python API (audit of 2026-11-27)


def _tiny_sim(mode=None):
    import abmpm

    scene = abmpm.Scene(simulation=abmpm.SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.04, fps=30),
                        materials=[abmpm.Fluid(name="water")],
                        bodies=[abmpm.BoxBody(material="water", min=(0.1, 0.1, 0.1), max=(0.2, 0.2, 0.2))])
    return abmpm.Simulation(scene, device="cpu", mode=mode)


@pytest.mark.parametrize("kw", [{"seconds": float("nan")}, {"seconds": float("inf")}, {"seconds": -1.0},
                                {"frames": -1}, {"frames": 1.7}, {"frames": True}, {"frames": "2"}])
def test_advance_refuses_what_it_cannot_run(kw):
    # seconds=nan ran for ever (the stop test never held); the others did nothing or ran a
    # frame count nobody asked for, without a word
    sim = _tiny_sim()
    with pytest.raises(ValueError, match=f"{next(iter(kw))}="):
        sim.advance(**kw)


@pytest.mark.parametrize("field, value, message", [
    ("material", 5, "material: values from 0 to 0"),  # a segfault in P2G for 1e6, wrong data for -1
    ("level", 1, "level: values from 0 to 0"),  # original mode has no fine grid: the particles froze
    ("mass", float("nan"), "mass: .* NaN"),
    ("volume", 0.0, "volume: every value must be > 0"),
    ("v", 1e40, "beyond single precision"),
    ("x", 5.0, "outside the domain"),
])
def test_set_particles_refuses_values_a_step_cannot_take(field, value, message):
    import numpy as np

    sim = _tiny_sim()
    shape = sim.state_dict()[0][field].shape
    with pytest.raises(ValueError, match=message):
        sim.set_particles(**{field: np.full(shape, value)})


def test_load_state_dict_refuses_another_modes_state():
    from abmpm.errors import AbmpmError

    arrays, meta = _tiny_sim("finest").state_dict()
    with pytest.raises(AbmpmError, match="finest run"):
        _tiny_sim("original").load_state_dict(arrays, meta)
    meta["mode"] = "original"  # the same arrays, relabelled: their level-1 particles still do not fit
    with pytest.raises(AbmpmError, match="level"):
        _tiny_sim("original").load_state_dict(arrays, meta)


def test_simulation_and_load_scene_name_what_they_expected():
    import abmpm
    from abmpm.errors import SceneError

    with pytest.raises(TypeError, match="abmpm.Scene"):
        abmpm.Simulation("dam_break")
    for bad, message in ((None, "expected a scene file"), ("", "empty"), ("a" * 300, "too long")):
        with pytest.raises(SceneError, match=message):
            abmpm.load_scene(bad)


def test_bench_checks_its_options_before_it_runs(tmp_path):
    for argv in (["--threads", "-1"], ["--seconds", "nan"], ["--frames", "0"], ["--json", str(tmp_path)],
                 ["--one-step", "0"], ["--one-step", "0.1"],  # one step is the interface suite's
                 ["--criterion", "both"], ["--criterion", "nearest"],  # so is the criterion, of these three
                 ["--halo", "2"], ["--halo", "-1"], ["--halo", "two"],  # and the halo
                 ["--coupling", "partition"], ["--coupling", "glue"]):  # and the coupling
        with pytest.raises(SystemExit) as exc:
            main(["bench", "--suite", "adaptive", *argv])
        assert exc.value.code == 2, argv


def test_bad_threads_environment_and_unservable_host(monkeypatch, tmp_path, capsys):
    monkeypatch.setenv("ABMPM_THREADS", "abc")
    assert main(["run", "dam_break", "--frames", "1", "--out", str(tmp_path / "o")]) == 2
    assert "ABMPM_THREADS='abc'" in capsys.readouterr().err
    monkeypatch.delenv("ABMPM_THREADS")
    pytest.importorskip("viser")
    assert main(["view", str(tmp_path), "--host", "nonsense.invalid"]) == 2  # it hung, silently
    assert "cannot serve the viewer on host" in capsys.readouterr().err
