"""Mesh obstacles and link shapes from files (STL, binary or ASCII; OBJ):
the same signed distance as the mesh given inline, a scale and a pose,
paths relative to the robot file, bad files named."""

import numpy as np
import pytest

from soft_twin_core.engine.contact import signed_distance
from soft_twin_core.errors import ModelError
from soft_twin_core.robot.obstacles import obstacle_from_dict
from test_contact import bumpy_sphere


def _binary_stl(V, F):
    rec = np.zeros(len(F), np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")]))
    rec["corners"] = V[F]
    return b"written by a test".ljust(80) + np.uint32(len(F)).tobytes() + rec.tobytes()


def _ascii_stl(V, F):
    out = ["solid rock"]
    for f in F:
        out += ["  facet normal 0 0 0", "    outer loop"] \
            + [f"      vertex {x!r} {y!r} {z!r}" for x, y, z in V[f].tolist()] + ["    endloop", "  endfacet"]
    return ("\n".join(out + ["endsolid rock"]) + "\n").encode()


def _obj(V, F):
    return ("# a test's mesh\n" + "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in V.tolist())
            + "".join(f"f {a + 1}/1 {b + 1} {c - len(V)}\n" for a, b, c in F)).encode()      # 1-based, negative


def test_an_stl_or_obj_file_gives_the_mesh_given_inline(tmp_path):
    """The bumpy sphere (not convex, 512 triangles) written as a binary STL,
    an ASCII STL and an OBJ (1-based, negative and slashed indices): each
    file's obstacle has the inline mesh's signed distance (STL: to its
    float32 corners)."""
    V, F = bumpy_sphere(3)
    inline = obstacle_from_dict({"name": "rock", "type": "mesh", "vertices": V.tolist(), "faces": F.tolist()}, "r")
    P = np.random.default_rng(3).standard_normal((400, 3)) * 0.05
    ref = signed_distance(inline, P)[0]
    for name, data, tol in (("rock.stl", _binary_stl(V, F), 1e-8), ("rock_ascii.stl", _ascii_stl(V, F), 1e-15),
                            ("rock.obj", _obj(V, F), 1e-15)):
        (tmp_path / name).write_bytes(data)
        ob = obstacle_from_dict({"name": "rock", "type": "mesh", "file": name}, "r", str(tmp_path))
        assert len(ob.triangles) == 512, name
        np.testing.assert_allclose(signed_distance(ob, P)[0], ref, atol=tol, rtol=0, err_msg=name)


def test_a_mesh_file_in_millimetres_placed_by_a_pose_is_the_box_it_draws(tmp_path):
    """A cube of quadrilaterals (an OBJ's polygons split into fans) in
    millimetres, scale 0.001, turned and placed by position and rpy: the
    box obstacle of the same size and pose, to round-off."""
    V = np.array([[x, y, z] for x in (-10, 10) for y in (-20, 20) for z in (-30, 30)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    (tmp_path / "block.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in V)
                                        + "".join("f " + " ".join(str(i + 1) for i in q) + "\n" for q in quads))
    pose = {"position": [0.1, -0.2, 0.3], "rpy": [0.3, -0.5, 1.1]}
    mesh = obstacle_from_dict({"name": "m", "type": "mesh", "file": "block.obj", "scale": 0.001, **pose}, "m",
                              str(tmp_path))
    box = obstacle_from_dict({"name": "b", "type": "box", "center": pose["position"], "rpy": pose["rpy"],
                              "size": [0.02, 0.04, 0.06]}, "b")
    P = np.array(pose["position"]) + np.random.default_rng(4).uniform(-0.06, 0.06, (500, 3))
    np.testing.assert_allclose(signed_distance(mesh, P)[0], signed_distance(box, P)[0], atol=1e-12)


def test_a_robot_file_s_mesh_file_is_found_beside_it(tmp_path):
    """A robot file's obstacle and a link's collision shape name mesh files
    relative to the robot file, wherever the process runs."""
    import yaml
    from soft_twin_core.robot.mechanism import load_mechanism
    V, F = bumpy_sphere(2)
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "rock.stl").write_bytes(_binary_stl(V * 2, F))
    d = {"name": "arm_and_rock", "segments": [{"name": "s", "length": 0.3, "sections": 4,
                                               "cross_section": {"shape": "solid_circle", "radius": 0.01},
                                               "material": {"youngs_modulus": 2e6, "density": 1100}}],
         "obstacles": [{"name": "rock", "type": "mesh", "file": "meshes/rock.stl", "position": [0.2, 0, -0.2]}]}
    (tmp_path / "arm.yaml").write_text(yaml.safe_dump(d))
    mech = load_mechanism(str(tmp_path / "arm.yaml"))
    assert len(mech.obstacles[0].triangles) == 128
    np.testing.assert_allclose(mech.obstacles[0].a, [0.2, 0, -0.2], atol=1e-6)
    tree = {"name": "held_rock", "bodies": [
        {"name": "rock", "type": "link", "parent": "base", "joint": {"type": "fixed"}, "mass": 0.1,
         "inertia": [1e-4, 1e-4, 1e-4, 0, 0, 0],
         "collision": {"shape": "mesh", "file": "meshes/rock.stl", "scale": 0.5}}]}
    (tmp_path / "tree.yaml").write_text(yaml.safe_dump(tree))
    (link,) = load_mechanism(str(tmp_path / "tree.yaml")).links
    assert len(link.collision.triangles) == 128
    corners = link.collision.triangles.reshape(-1, 3) @ link.collision.rotation.T + link.collision.a
    np.testing.assert_allclose(np.abs(corners).max(axis=0), np.abs(V).max(axis=0), rtol=1e-6)   # 2 V at scale 0.5


@pytest.mark.parametrize("entry, content, message", [
    ({"file": "none.stl"}, None, r"\.file: cannot read '.*none\.stl'"),
    ({"file": "rock.ply"}, b"ply", r"\.file: 'rock\.ply': expected an \.stl or \.obj file"),
    ({"file": "rock.stl"}, b"x" * 80 + np.uint32(3).tobytes() + b"y" * 100, "neither a binary STL"),
    ({"file": "rock.obj"}, b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r"line 4: a face needs 3 or more indices"),
    ({"file": "rock.obj"}, b"v 0 0 zero\n", r"line 1: expected numbers"),
    ({"file": "rock.obj", "vertices": [[0, 0, 0]]}, b"", "either 'file' or 'vertices' and 'faces', not both"),
    ({"vertices": [[0, 0, 0]], "faces": [[0, 0, 0]], "scale": 2}, None, r"\.scale: scales a mesh 'file'"),
    ({"file": "rock.obj", "scale": -1}, b"", r"\.scale"),
])
def test_a_bad_mesh_file_is_refused_naming_the_field_and_the_file(tmp_path, entry, content, message):
    if content is not None:
        (tmp_path / entry["file"]).write_bytes(content)
    with pytest.raises(ModelError, match=message):
        obstacle_from_dict({"name": "rock", "type": "mesh", **entry}, "robot.obstacles[0]", str(tmp_path))
