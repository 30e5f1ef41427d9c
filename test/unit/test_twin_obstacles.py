"""Obstacles that change at run time (issue 27): placed from a pose (what
the node's ~/obstacles messages give), and added, moved and removed on a
running twin, in both modes."""

import math

import numpy as np
import pytest

from soft_twin_core.engine.contact import signed_distance
from soft_twin_core.errors import ModelError
from soft_twin_core.robot.mechanism import load_mechanism
from soft_twin_core.robot.model import find_file
from soft_twin_core.robot.obstacles import obstacle_at, obstacle_placed
from soft_twin_core.twin import Twin, TwinSettings


def _pose(z=0.0, angle=0.0, x=0.0):
    """A pose at (x, 0, z), turned by ``angle`` about y."""
    T = np.eye(4)
    c, s = math.cos(angle), math.sin(angle)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = [x, 0.0, z]
    return T


def test_obstacles_are_placed_by_a_pose():
    """A plane through the pose's origin with its z axis as the normal; a
    sphere and a box centred, the box along the pose's axes; a capsule along
    z, centred: signed distances of known points. A move keeps the shape and
    the law."""
    a = math.pi / 2                                       # z axis -> +x
    law = {"friction": 0.4, "damping": 0.1}
    plane = obstacle_at("wall", "plane", _pose(angle=a, x=0.2), law=law)
    assert signed_distance(plane, np.array([[0.5, 0.3, 0.1]]))[0][0] == pytest.approx(0.3)
    assert plane.friction == 0.4 and plane.damping == 0.1
    ball = obstacle_at("ball", "sphere", _pose(z=1.0), [0.1])
    assert signed_distance(ball, np.array([[0.0, 0.0, 1.5]]))[0][0] == pytest.approx(0.4)
    box = obstacle_at("box", "box", _pose(angle=a), [0.2, 0.4, 0.6])     # its z edge (0.6) along world x
    assert signed_distance(box, np.array([[0.5, 0.0, 0.0], [0.0, 0.0, 0.3]]))[0] == pytest.approx([0.2, 0.2])
    rod = obstacle_at("rod", "capsule", _pose(angle=a), [0.4, 0.05])     # from x = -0.2 to 0.2
    assert rod.a == pytest.approx([-0.2, 0, 0]) and rod.b == pytest.approx([0.2, 0, 0]) and rod.radius == 0.05
    moved = obstacle_placed(rod, _pose(z=1.0))                          # now upright at z = 1
    assert moved.a == pytest.approx([0, 0, 0.8]) and moved.b == pytest.approx([0, 0, 1.2])
    box2 = obstacle_placed(box, _pose(z=2.0))
    assert box2.half_size == pytest.approx(box.half_size) and box2.rotation == pytest.approx(np.eye(3))
    assert obstacle_placed(plane, _pose(z=0.1)).friction == 0.4


@pytest.mark.parametrize("kind, dims, message", [
    ("sphere", [], "ball.dimensions: a sphere needs 1 dimensions"),
    ("sphere", [-0.1], "ball.radius: must be > 0"),
    ("box", [0.1, 0.0, 0.1], "ball.size: the box's edge lengths must be > 0 m"),
    ("capsule", [0.0, 0.1], "ball: 'from' and 'to' must differ"),
    ("cone", [0.1], "ball.type: expected one of"),
])
def test_bad_shapes_are_refused_naming_the_field(kind, dims, message):
    with pytest.raises(ModelError, match=message.replace("(", r"\(")):
        obstacle_at("ball", kind, np.eye(4), dims, where="ball")


def test_a_move_to_a_pose_that_is_not_finite_is_refused():
    T = _pose()
    T[0, 3] = math.nan
    with pytest.raises(ModelError, match="'ball': the pose must be finite"):
        obstacle_placed(obstacle_at("ball", "sphere", np.eye(4), [0.1]), T)


@pytest.fixture(scope="module")
def arm():
    return load_mechanism(find_file("tendon_arm", "robots"))


def test_a_floor_added_and_raised_under_a_running_twin_meets_the_arm(arm):
    """Dynamic twin of the drooping default arm (tip at z = -0.297 m): a
    floor added below it touches nothing; raised 2 mm a step, it meets the
    tip, pushes it up (the contacts see the floor's motion) and carries it;
    removed, the arm falls free again, on the compiled path. Names stay
    unique."""
    tw = Twin(arm, TwinSettings(mode="dynamic", dt=0.005))
    z_rest = tw.outputs().tip_pose[2, 3]
    assert z_rest == pytest.approx(-0.2974, abs=1e-3)
    tw.set_obstacles([obstacle_at("floor", "plane", _pose(z=-0.31))])
    assert tw.step(5).converged and not len(tw.contacts)
    z = -0.31
    touched = 0
    for _ in range(10):
        z += 0.002
        tw.set_obstacles([obstacle_at("floor", "plane", _pose(z=z))])        # same name and kind: a move
        assert tw.step(1).converged
        assert tw.obstacles[0].a[2] == pytest.approx(z)
        touched += len(tw.contacts) > 0
    assert touched >= 1
    info = tw.step(100)
    assert info.converged and len(tw.contacts) >= 1
    tip = tw.outputs().tip_pose[:3, 3]
    assert tip[2] > z and tip[2] > z_rest + 0.005                 # resting on the raised floor
    assert np.all(tw.contacts.gap > -1e-4) and np.all(tw.contacts.force[:, 2] > 0)
    tw.set_obstacles([])
    assert tw.step(1).converged and tw.contacts is None and tw.obstacles == ()
    with pytest.raises(ModelError, match=r"obstacle names must be unique, repeated: \['a'\]"):
        tw.set_obstacles([obstacle_at("a", "sphere", np.eye(4), [0.1])] * 2)


def test_a_quasi_static_twin_solves_with_a_new_obstacle_and_rests_on_it_after_a_reset(arm):
    tw = Twin(arm, TwinSettings(mode="quasi_static"))
    tw.set_obstacles([obstacle_at("floor", "plane", _pose(z=-0.29))])
    assert tw.needs_solve
    info = tw.step()
    assert info.converged and len(tw.contacts) >= 1
    assert tw.outputs().tip_pose[2, 3] > -0.29
    snap = tw.outputs()
    assert [o.name for o in snap.obstacles] == ["floor"]
    tw.reset()                                   # the rest shape is solved again, on the floor
    assert len(tw.rest_contacts) >= 1 and tw.outputs().tip_pose[2, 3] > -0.29


# --- the node's messages (soft_twin/Obstacle in, soft_twin/Contacts out) ------

def _msg(name, op, plane=False, kind=0, dims=(), z=0.0, **law):
    pytest.importorskip("shape_msgs", reason="needs the ROS message packages")
    from geometry_msgs.msg import Pose
    from shape_msgs.msg import SolidPrimitive
    from soft_twin.msg import Obstacle
    m = Obstacle(name=name, operation=op, plane=plane, primitive=SolidPrimitive(type=kind, dimensions=list(dims)),
                 pose=Pose(), **law)
    m.pose.position.z = z
    m.pose.orientation.w = 1.0
    return m


def test_obstacle_messages_add_move_and_remove_and_bad_ones_are_counted_not_applied():
    """ADD a plane (law fields: 0 = default), a sphere (SPHERE) and a
    capsule (CYLINDER: height, radius); MOVE the sphere; REMOVE the plane;
    the bad messages come back as InputErrors with their reason, the
    obstacles as the good ones left them."""
    from soft_twin import inputs
    batch = [(_msg("floor", 0, plane=True, z=-0.3, friction=0.5), None),
             (_msg("ball", 0, kind=2, dims=[0.05], z=0.1, torsional_friction=0.002), None),
             (_msg("post", 0, kind=3, dims=[0.2, 0.01]), None),
             (_msg("ball", 1, z=0.2), None),
             (_msg("ghost", 1), None),                           # unknown_name
             (_msg("cone", 0, kind=4, dims=[0.1, 0.1]), None),    # bad_obstacle: no cones
             (_msg("big", 0, kind=2, dims=[-1.0]), None),         # bad_obstacle: the radius named
             (_msg("floor", 2), None)]
    bad_pose = _msg("ball", 1)
    bad_pose.pose.position.x = math.inf
    batch.insert(4, (bad_pose, None))                             # non_finite
    obstacles, n, errors = inputs.fold_obstacles(batch, ())
    assert n == 5 and [e.reason for e in errors] == ["non_finite", "unknown_name", "bad_obstacle", "bad_obstacle"]
    assert "radius: must be > 0" in str(errors[-1]) and "primitive.type 4" in str(errors[-2])
    assert [o.name for o in obstacles] == ["ball", "post"]
    ball, post = obstacles
    assert ball.a == pytest.approx([0, 0, 0.2]) and ball.radius == 0.05 and ball.torsional_friction == 0.002
    assert post.kind == "capsule" and post.a == pytest.approx([0, 0, -0.1]) and post.radius == 0.01
    floor = inputs.fold_obstacles(batch[:1], ())[0][0]
    assert floor.friction == 0.5 and floor.stiffness is None and floor.b == pytest.approx([0, 0, 1])


def test_the_contacts_message_has_each_contact_with_its_normal_force(arm):
    pytest.importorskip("shape_msgs", reason="needs the ROS message packages")
    from std_msgs.msg import Header
    from soft_twin import conversions as cv
    tw = Twin(arm, TwinSettings(mode="quasi_static"))
    tw.set_obstacles([obstacle_at("floor", "plane", _pose(z=-0.29))])
    tw.step()
    snap = tw.outputs()
    msg = cv.contacts_msg(arm, snap.contacts, snap.obstacles, Header(frame_id="base_link"))
    assert len(msg.contacts) == len(snap.contacts) >= 1 and msg.header.frame_id == "base_link"
    c = msg.contacts[0]
    assert c.obstacle == "floor" and c.member == arm.members[0].name
    assert c.normal.z == pytest.approx(1.0) and c.normal_force == pytest.approx(c.force.z) and c.normal_force > 0
    assert 0 < c.s <= 0.45
    assert cv.contacts_msg(arm, None, (), Header()).contacts == []


def test_a_bad_obstacles_file_is_refused_naming_the_file_and_the_field(tmp_path):
    from soft_twin.config import ConfigError, load_obstacles
    assert load_obstacles("") == ()
    with pytest.raises(ConfigError, match="obstacles_file: 'nowhere.yaml' does not exist"):
        load_obstacles("nowhere.yaml")
    f = tmp_path / "o.yaml"
    f.write_text("obstacle:\n  - {name: a, type: sphere, center: [0, 0, 0], radius: 0.1}\n")
    with pytest.raises(ConfigError, match="expected a mapping with one key, 'obstacles'"):
        load_obstacles(str(f))
    f.write_text("obstacles:\n  - {name: a, type: sphere, center: [0, 0, .nan], radius: 0.1}\n")
    with pytest.raises(ConfigError, match=r"obstacles\[0\]\.center"):
        load_obstacles(str(f))
    f.write_text("obstacles:\n  - {name: a, type: sphere, center: [0, 0, 0], radius: 0.1}\n")
    assert [o.name for o in load_obstacles(str(f))] == ["a"]
    # a mesh file beside the obstacles file (the node's working directory elsewhere)
    (tmp_path / "tet.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    f.write_text("obstacles:\n  - {name: tet, type: mesh, file: tet.obj, scale: 0.01}\n")
    (tet,) = load_obstacles(str(f))
    assert len(tet.triangles) == 4 and np.ptp(tet.triangles.reshape(-1, 3), axis=0) == pytest.approx([0.01] * 3)
    f.write_text("obstacles:\n  - {name: tet, type: mesh, file: gone.obj}\n")
    with pytest.raises(ConfigError, match=r"obstacles\[0\]\.file: cannot read"):
        load_obstacles(str(f))


def test_a_mesh_obstacle_message_is_a_convex_mesh_in_its_pose_frame():
    """ADD with a shape_msgs/Mesh (primitive type 0): the vertices in the
    pose's frame; a MOVE places that frame; a mesh that is not closed is
    rejected (bad_obstacle), naming the edge."""
    pytest.importorskip("shape_msgs", reason="needs the ROS message packages")
    from geometry_msgs.msg import Point
    from shape_msgs.msg import MeshTriangle
    from soft_twin import inputs
    V = [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]]
    F = [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]                  # (any orientation)
    m = _msg("wedge", 0, z=1.0)
    m.mesh.vertices = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in V]
    m.mesh.triangles = [MeshTriangle(vertex_indices=f) for f in F]
    (ob,), n, errors = inputs.fold_obstacles([(m, None)], ())
    assert n == 1 and not errors and ob.kind == "mesh"
    # the face x + y + z = 0.1 of the wedge, lifted by 1 m: a point 0.05 m outside it along its normal
    p = np.array([[0.1 / 3, 0.1 / 3, 1.0 + 0.1 / 3]]) + 0.05 / math.sqrt(3)
    assert signed_distance(ob, p)[0][0] == pytest.approx(0.05)
    assert signed_distance(ob, np.array([[0.01, 0.01, 0.9]]))[0][0] == pytest.approx(0.1)    # below its base
    moved, n, _ = inputs.fold_obstacles([(_msg("wedge", 1, z=2.0), None)], (ob,))
    assert signed_distance(moved[0], p + [0, 0, 1.0])[0][0] == pytest.approx(0.05)
    m.mesh.triangles = m.mesh.triangles[:3] + [MeshTriangle(vertex_indices=F[0])]     # a face twice, one missing
    _, n, errors = inputs.fold_obstacles([(m, None)], ())
    assert n == 0 and errors[0].reason == "bad_obstacle" and "the mesh is not closed: edge" in str(errors[0])
