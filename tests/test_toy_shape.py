"""A new collider shape is one new file plus one registry line.

The test copies the package, writes one module for a toy shape (a square frame:
a flat sheet with a square hole, its own builder in the same file) into
``geometry/collider_shapes/`` and adds its name to ``MODULES``, changing exactly one
line. Then, in a fresh interpreter on that copy:

* a TOML scene with ``shape = "frame"`` loads with the toy's defaults, and a typo in
  one of its keys, or a value its declared kind forbids, is refused naming the field
  (the schema came from the module's declaration);
* the collider's mesh is the builder's, called with the declared parameters and
  placed at the collider's center: its bounds are the frame's outer square (the
  vertices are exact float64 sums, so 1e-12 m).
"""

import textwrap

TOY = textwrap.dedent(
    '''
    """A square frame in the xz-plane: a sheet with a square hole (test of the shape registry)."""

    import numpy as np
    import trimesh

    from . import ColliderShape, ShapeParameter


    def frame(outer=1.0, hole=0.5):
        if not 0.0 < hole < outer:
            raise ValueError(f"the hole ({hole}) must be smaller than the frame ({outer})")
        a, b = outer / 2, hole / 2
        ring = [(-a, -a), (a, -a), (a, a), (-a, a), (-b, -b), (b, -b), (b, b), (-b, b)]
        v = np.array([(x, 0.0, z) for x, z in ring])
        f = [(0, 5, 1), (0, 4, 5), (1, 6, 2), (1, 5, 6), (2, 7, 3), (2, 6, 7), (3, 4, 0), (3, 7, 4)]
        return trimesh.Trimesh(v, np.array(f), process=False)


    SHAPE = ColliderShape("frame", frame, (
        ShapeParameter("outer", "positive", 0.4, "side of the frame, m"),
        ShapeParameter("hole", "positive", 0.2, "side of the hole, m"),
    ), __doc__)
    '''
)

SCENE = textwrap.dedent(
    """
    name = "toy shape"
    [simulation]
    dx = 0.05
    [[materials]]
    name = "water"
    model = "fluid"
    [[bodies]]
    shape = "box"
    material = "water"
    min = [0.4, 0.6, 0.4]
    max = [0.6, 0.8, 0.6]
    [[colliders]]
    shape = "frame"
    center = [0.5, 0.3, 0.5]
    """
)

CHECK = textwrap.dedent(
    """
    import json, sys
    from abmpm.errors import SceneError
    from abmpm.geometry.collider_shapes import MODULES
    from abmpm.geometry.placement import collider_mesh
    from abmpm.scene.loader import load_scene

    out = {"modules": list(MODULES)}
    scene = load_scene(sys.argv[1])
    c = scene.colliders[0]
    out["defaults"] = [c.outer, c.hole]
    out["bounds"] = collider_mesh(c).bounds.tolist()
    out["errors"] = []
    for bad in sys.argv[2:]:
        try:
            load_scene(bad)
        except SceneError as exc:
            out["errors"].append(str(exc))
    print("RESULT " + json.dumps(out))
    """
)


def test_a_new_collider_shape_is_one_file_and_one_registry_line(tmp_path, registry_copy):
    registry_copy.register("geometry/collider_shapes", "frame", TOY, last="perforated_plate")
    scene = tmp_path / "toy.toml"
    scene.write_text(SCENE)
    bad = []
    for i, extra in enumerate(("outre = 0.5", "hole = -0.1")):
        bad.append(tmp_path / f"bad{i}.toml")
        bad[-1].write_text(SCENE + extra + "\n")
    out = registry_copy.run(CHECK, scene, *bad, timeout=300)

    assert out["modules"][-1] == "frame"
    assert out["defaults"] == [0.4, 0.2]
    (lo, hi) = out["bounds"]
    assert max(abs(a - b) for a, b in zip(lo, [0.3, 0.3, 0.3])) < 1e-12
    assert max(abs(a - b) for a, b in zip(hi, [0.7, 0.3, 0.7])) < 1e-12
    assert len(out["errors"]) == 2
    assert "colliders[0].outre: unknown key" in out["errors"][0]
    assert out["errors"][1].endswith("colliders[0].hole: must be > 0")
