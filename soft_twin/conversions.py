"""numpy <-> ROS message conversions (no computation beyond a change of
representation). Poses are 4x4 homogeneous matrices; quaternions are
[x, y, z, w] as in geometry_msgs."""

import numpy as np
from geometry_msgs.msg import Point, Pose, PoseArray, Quaternion, Vector3, Wrench

_AXIS = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float)   # columns: x -> z rotation


def quaternions_from_matrices(R):
    """Unit quaternions [x, y, z, w] (..., 4) of rotation matrices (..., 3, 3)
    (Shepperd's method: the largest of w, x, y, z is computed first, so it
    stays accurate for every rotation), with w >= 0."""
    R = np.asarray(R, dtype=float)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([tr, m00, m11, m22], axis=-1)
    k = np.argmax(cand, axis=-1)
    q = np.empty(R.shape[:-2] + (4,))
    # t = 2 |largest component|: sqrt(1 + tr) for w, sqrt(1 + 2 m_ii - tr) for x, y, z;
    # the other components follow from off-diagonal sums/differences / (2 t)
    t = np.sqrt(np.maximum(1.0 + cand.max(axis=-1) * 2.0 - tr, 1e-300))
    w_case = k == 0
    x_case, y_case, z_case = k == 1, k == 2, k == 3
    r21, r12 = R[..., 2, 1], R[..., 1, 2]
    r02, r20 = R[..., 0, 2], R[..., 2, 0]
    r10, r01 = R[..., 1, 0], R[..., 0, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = 0.5 / t
        q[..., 3] = np.where(w_case, 0.5 * t, np.where(x_case, (r21 - r12) * s,
                             np.where(y_case, (r02 - r20) * s, (r10 - r01) * s)))
        q[..., 0] = np.where(x_case, 0.5 * t, np.where(w_case, (r21 - r12) * s,
                             np.where(y_case, (r01 + r10) * s, (r02 + r20) * s)))
        q[..., 1] = np.where(y_case, 0.5 * t, np.where(w_case, (r02 - r20) * s,
                             np.where(x_case, (r01 + r10) * s, (r12 + r21) * s)))
        q[..., 2] = np.where(z_case, 0.5 * t, np.where(w_case, (r10 - r01) * s,
                             np.where(x_case, (r02 + r20) * s, (r12 + r21) * s)))
    q = q * np.where(q[..., 3:4] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def matrix_from_quaternion(x, y, z, w):
    """3x3 rotation of a quaternion (normalised here); ValueError if zero/non-finite."""
    q = np.array([x, y, z, w], dtype=float)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"quaternion {q.tolist()} is zero or not finite")
    x, y, z, w = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def pose_msgs(T):
    """geometry_msgs/Pose list from poses (N, 4, 4)."""
    T = np.asarray(T, dtype=float)
    quats = quaternions_from_matrices(T[:, :3, :3]).tolist()
    out = []
    for p, o in zip(T[:, :3, 3].tolist(), quats):
        m = Pose()
        pp, oo = m.position, m.orientation
        pp.x, pp.y, pp.z = p
        oo.x, oo.y, oo.z, oo.w = o
        out.append(m)
    return out


def pose_msg(T):
    return pose_msgs(np.asarray(T, dtype=float)[None])[0]


def pose_array(T, header=None):
    msg = PoseArray()
    if header is not None:
        msg.header = header
    msg.poses = pose_msgs(T)
    return msg


def matrix_from_pose(pose):
    """4x4 from a geometry_msgs/Pose (quaternion normalised; ValueError if invalid)."""
    p, o = pose.position, pose.orientation
    pos = np.array([p.x, p.y, p.z], dtype=float)
    if not np.all(np.isfinite(pos)):
        raise ValueError(f"position {pos.tolist()} is not finite")
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(o.x, o.y, o.z, o.w)
    T[:3, 3] = pos
    return T


def wrench_msg(w):
    """geometry_msgs/Wrench from [f; m] (6,)."""
    w = [float(x) for x in w]
    return Wrench(force=Vector3(x=w[0], y=w[1], z=w[2]), torque=Vector3(x=w[3], y=w[4], z=w[5]))


def wrench_parts(msg):
    """(force (3,), torque (3,)) lists of a geometry_msgs/Wrench."""
    f, t = msg.force, msg.torque
    return [f.x, f.y, f.z], [t.x, t.y, t.z]


def cylinder_orientation(T):
    """Quaternions (N, 4) turning RViz's cylinder axis (z) onto each pose's
    x axis (the backbone tangent)."""
    R = np.asarray(T, dtype=float)[:, :3, :3] @ _AXIS
    return quaternions_from_matrices(R)


def point(p):
    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def quaternion(q):
    return Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


# --- contact (issue 27): soft_twin/Obstacle in, soft_twin/Contacts out ---------

_PRIMITIVES = {1: ("box", 3), 2: ("sphere", 1), 3: ("capsule", 2)}    # shape_msgs/SolidPrimitive BOX, SPHERE, CYLINDER
_LAW = ("stiffness", "smoothing", "damping", "friction", "stiction_velocity", "torsional_friction")


def obstacles_after(msg, obstacles):
    """The obstacles (a tuple) after one soft_twin/Obstacle message: ADD (or
    replace), MOVE or REMOVE the obstacle ``msg.name``; InputError (reason
    bad_obstacle, unknown_name or non_finite) naming the field, the
    obstacles unchanged."""
    from soft_twin_core.errors import InputError, ModelError
    from soft_twin_core.robot.obstacles import obstacle_at, obstacle_placed
    name, op = msg.name, msg.operation
    if not name:
        raise InputError("bad_obstacle", "obstacle: name must not be empty")
    names = [o.name for o in obstacles]
    if op not in (0, 1, 2):
        raise InputError("bad_obstacle", f"obstacle {name!r}: operation {op} is none of ADD (0), MOVE (1), "
                                         f"REMOVE (2)")
    if op != 0 and name not in names:
        raise InputError("unknown_name", f"obstacle {name!r}: no such obstacle to {('move', 'remove')[op - 1]} "
                                         f"(there are {names})")
    if op == 2:
        return tuple(o for o in obstacles if o.name != name)
    try:
        T = matrix_from_pose(msg.pose)
    except ValueError as e:
        raise InputError("non_finite", f"obstacle {name!r}: pose: {e}") from None
    try:
        if op == 1:
            new = obstacle_placed(obstacles[names.index(name)], T)
        else:
            law = {k: float(getattr(msg, k)) for k in _LAW if getattr(msg, k) != 0.0}
            mesh = None
            if msg.plane:
                kind, dims = "plane", ()
            elif msg.primitive.type in _PRIMITIVES:
                kind, dims = _PRIMITIVES[msg.primitive.type][0], list(msg.primitive.dimensions)
            elif msg.primitive.type == 0 and len(msg.mesh.triangles):
                kind, dims = "mesh", ()
                mesh = ([[v.x, v.y, v.z] for v in msg.mesh.vertices],
                        [[int(i) for i in t.vertex_indices] for t in msg.mesh.triangles])
            else:
                raise InputError("bad_obstacle", f"obstacle {name!r}: primitive.type {msg.primitive.type}: "
                                                 f"expected BOX (1), SPHERE (2) or CYLINDER (3), a mesh with "
                                                 f"triangles, or plane = true")
            new = obstacle_at(name, kind, T, dims, law, where=f"obstacle {name!r}", mesh=mesh)
    except ModelError as e:
        raise InputError("bad_obstacle", str(e)) from None
    if name in names:
        return tuple(new if o.name == name else o for o in obstacles)
    return tuple(obstacles) + (new,)


def contacts_msg(mech, contacts, obstacles, header):
    """soft_twin/Contacts of a ContactState (None: none) of ``mech``
    against ``obstacles`` (those it indexes)."""
    from soft_twin.msg import Contact, Contacts
    from soft_twin_core.solve.contact import contacts_dict
    out = Contacts(header=header)
    for c in contacts_dict(mech, contacts, obstacles):
        f, n = np.asarray(c["force"]), np.asarray(c["normal"])
        out.contacts.append(Contact(
            member=c["member"], s=c["s"], obstacle=c["obstacle"], position=Point(**dict(zip("xyz", c["position"]))),
            normal=Vector3(**dict(zip("xyz", c["normal"]))), gap=c["gap"], force=Vector3(**dict(zip("xyz", c["force"]))),
            normal_force=float(f @ n), slip_velocity=Vector3(**dict(zip("xyz", c["slip"])))))
    return out
