"""Joint kinds (plain numpy, one joint at a time): transform, motion
subspace and its time derivative, integration on the joint's group.

Conventions as in :mod:`soft_twin_core.engine.multibody`: the subspace maps the
joint velocity v_i to the body twist of the output frame relative to the
input frame, expressed in the output frame. Quaternions are [x, y, z, w]
(as Pinocchio). The compiled passes (:mod:`soft_twin_core.engine.kernels`)
implement the same formulas; these are the readable reference.
"""

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine.joint_kinds import FREE, PRISMATIC, REVOLUTE, SOFT, SPHERICAL


def quat_to_rot(quat):
    """Rotation matrix of a unit quaternion [x, y, z, w]."""
    x, y, z, w = quat
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rot_to_quat(R):
    """Unit quaternion [x, y, z, w] (w >= 0) of a rotation matrix."""
    from scipy.spatial.transform import Rotation
    q = Rotation.from_matrix(R).as_quat()
    return q if q[3] >= 0 else -q


def _quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _quat_exp(w):
    t = np.sqrt(np.dot(w, w))
    if t < 1e-8:
        s = 0.5 - t * t / 48.0
    else:
        s = np.sin(0.5 * t) / t
    return np.array([s * w[0], s * w[1], s * w[2], np.cos(0.5 * t)])


def section_strain(section, q_i):
    """Full 6-strain f of a soft section: f0 with the free modes set to q_i."""
    f = np.array(section.f0, dtype=np.result_type(q_i, float))
    f[section.modes] = q_i
    return f


def section_maps(section):
    """(map, tangent, tangent derivative) of the section's kinematic map."""
    if section.kinematic_map == "cayley":
        def tdot(x, xd):
            h = 1e-30          # T_cay is rational in x: the complex step is exact
            return lie.T_cay_se3(x + 1j * h * xd).imag / h
        return lie.cay_se3, lie.T_cay_se3, tdot
    return lie.exp_se3, lie.T_se3, lie.T_se3_dot


def joint_transform(joint, q_i):
    """4x4 transform input -> output frame for the joint's coordinates q_i."""
    k = joint.kind
    H = np.eye(4, dtype=np.result_type(q_i, float))
    if k == REVOLUTE:
        H[:3, :3] = lie.exp_so3(joint.axis * q_i[0])
    elif k == PRISMATIC:
        H[:3, 3] = joint.axis * q_i[0]
    elif k == SPHERICAL:
        H[:3, :3] = quat_to_rot(q_i)
    elif k == FREE:
        H[:3, :3] = quat_to_rot(q_i[3:7])
        H[:3, 3] = q_i[:3]
    elif k == SOFT:
        expmap = section_maps(joint.section)[0]
        return expmap(joint.section.length * section_strain(joint.section, q_i))
    return H


def point_transform(joint, q_i, x):
    """Soft joint: pose of the cross-section at abscissa x from the input frame."""
    expmap = section_maps(joint.section)[0]
    return expmap(x * section_strain(joint.section, q_i))


def subspace(joint, q_i, x=None):
    """Motion subspace S (6 x nv) in the output frame; for a soft joint with
    ``x`` given, the subspace x T(x f) B of the cross-section at abscissa x."""
    k = joint.kind
    S = np.zeros((6, joint.nv), dtype=np.result_type(q_i, float))
    if k == REVOLUTE:
        S[3:, 0] = joint.axis
    elif k == PRISMATIC:
        S[:3, 0] = joint.axis
    elif k == SPHERICAL:
        S[3:, :] = np.eye(3)
    elif k == FREE:
        S[:, :] = np.eye(6)
    elif k == SOFT:
        sec = joint.section
        x = sec.length if x is None else x
        T = section_maps(sec)[1](x * section_strain(sec, q_i))
        S = x * T[:, sec.modes]
    return S


def subspace_dot(joint, q_i, v_i, x=None):
    """Time derivative of :func:`subspace` along v_i (zero but for soft joints)."""
    if joint.kind != SOFT:
        return np.zeros((6, joint.nv))
    sec = joint.section
    x = sec.length if x is None else x
    fd = np.zeros(6, dtype=np.result_type(v_i, float))
    fd[sec.modes] = v_i
    Td = section_maps(sec)[2](x * section_strain(sec, q_i), x * fd)
    return x * Td[:, sec.modes]


def integrate(model, q, v):
    """q (+) v: the configuration reached from q by the constant velocity v
    in unit time, on each joint's group (quaternion or SE(3) exponential of
    the body velocity for spherical and free joints, addition otherwise)."""
    out = np.array(q, dtype=float)
    for i, j in enumerate(model.joints):
        a, b = model.idx_q[i], model.idx_v[i]
        if j.kind == SPHERICAL:
            out[a:a + 4] = _quat_mul(q[a:a + 4], _quat_exp(v[b:b + 3]))
        elif j.kind == FREE:
            H = joint_transform(j, q[a:a + 7]) @ lie.exp_se3(v[b:b + 6])
            out[a:a + 3] = H[:3, 3]
            out[a + 3:a + 7] = _quat_mul(q[a + 3:a + 7], _quat_exp(v[b + 3:b + 6]))
        elif j.nq:
            out[a:a + j.nq] = q[a:a + j.nq] + v[b:b + j.nv]
    return out


def difference(model, q1, q2):
    """v with integrate(q1, v) = q2 (log on each joint's group)."""
    out = np.zeros(model.nv)
    for i, j in enumerate(model.joints):
        a, b = model.idx_q[i], model.idx_v[i]
        if j.kind == SPHERICAL:
            out[b:b + 3] = lie.log_so3(quat_to_rot(q1[a:a + 4]).T @ quat_to_rot(q2[a:a + 4]))
        elif j.kind == FREE:
            H1, H2 = joint_transform(j, q1[a:a + 7]), joint_transform(j, q2[a:a + 7])
            out[b:b + 6] = lie.log_se3(lie.se3_inv(H1) @ H2)
        elif j.nq:
            out[b:b + j.nv] = q2[a:a + j.nq] - q1[a:a + j.nq]
    return out


def random_configuration(model, rng, scale=1.0):
    """A random q near q0 (soft strains within +-scale/L rad/m of f0 for the
    angular modes, +-0.1 scale for linear ones; random unit quaternions)."""
    q = model.q0.copy()
    for i, j in enumerate(model.joints):
        a = model.idx_q[i]
        if j.kind == SOFT:
            m = j.section.modes
            amp = np.where(m < 3, 0.1 * scale, scale / j.section.length)
            q[a:a + j.nq] += amp * rng.uniform(-1, 1, j.nq)
        elif j.kind in (REVOLUTE, PRISMATIC):
            q[a] = scale * rng.uniform(-np.pi, np.pi) if j.kind == REVOLUTE else scale * rng.uniform(-0.5, 0.5)
        elif j.kind == SPHERICAL:
            u = rng.normal(size=4)
            q[a:a + 4] = u / np.linalg.norm(u)
        elif j.kind == FREE:
            u = rng.normal(size=4)
            q[a:a + 3] = rng.uniform(-1, 1, 3)
            q[a + 3:a + 7] = u / np.linalg.norm(u)
    return q
