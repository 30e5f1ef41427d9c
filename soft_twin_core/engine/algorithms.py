"""Public multibody algorithms: thin wrappers over the compiled passes of
:mod:`soft_twin_core.engine.kernels.passes`, checked at entry.

Each takes ``(model, ws, q, ...)``, writes into the workspace ``ws`` and
returns views of it (copy what you keep). Conventions of
:mod:`soft_twin_core.engine.multibody`; gravity is the model's unless given.
"""

import numpy as np

from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import LoadArrays, empty_loads, kernel_array
from soft_twin_core.engine.kernels.derivatives import rnea_derivatives_pass
from soft_twin_core.engine.kernels.frames import point_poses as _poses, spatial_jacobian, spatial_jacobian_dot
from soft_twin_core.lie import Ad_inv, ad

_NO_LOADS = empty_loads()


def _enter(model, ws, q, v=None, a=None):
    ws.check(model)
    q = kernel_array(model.check_q(q))
    v = ws.zeros_v if v is None else kernel_array(model.check_v(v))
    a = ws.zeros_v if a is None else kernel_array(model.check_v(a, "a"))
    return q, v, a


def forward_kinematics(model, ws, q, v=None, a=None):
    """World poses of every joint's input and output frame, (g_in, g_out)
    each (n, 4, 4); with v (and a), body twists ``ws.work.V`` (and
    accelerations ``ws.work.A``) of the output frames."""
    level = 0 if v is None else (1 if a is None else 2)
    q, v, a = _enter(model, ws, q, v, a)
    passes.forward_pass(ws.m, ws.w, q, v, a, level)
    ws.level = level
    return ws.work.g_in, ws.work.g_out


def rnea(model, ws, q, v, a, loads=None, gravity=None, elastic=True):
    """Inverse dynamics, recursive Newton-Euler:
    ``tau = M a + C v + g(q) + K (q - q0) + D v - J^T F_ext`` (``elastic=False``
    leaves out stiffness and damping). ``loads``: a :class:`LoadArrays`.
    ``ws.work.f_in[i]`` is then the wrench the parent side exerts on joint
    i's subtree through its input frame (body axes), ``ws.work.f[i]`` the
    one at its output frame."""
    q, v, a = _enter(model, ws, q, v, a)
    g = kernel_array(model.gravity if gravity is None else gravity)
    passes.forward_pass(ws.m, ws.w, q, v, a, 2)
    ws.level = 2
    passes.rnea_pass(ws.m, ws.w, _NO_LOADS if loads is None else loads, g, ws.tau, False)
    if elastic:
        passes.joint_forces(ws.m, q, v, ws.tau)
    return ws.tau


def crba(model, ws, q):
    """Joint-space mass matrix M(q) (nv, nv), composite rigid body algorithm."""
    q, _, _ = _enter(model, ws, q)
    passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
    ws.level = 0
    passes.crba_pass(ws.m, ws.w, ws.M)
    return ws.M


def factor(model, ws, q, c_damping=0.0, c_stiffness=0.0):
    """Articulated-body factorisation of ``M(q) + c_damping D + c_stiffness K``
    (D, K: the joint-space damping and stiffness blocks) in O(n); solve with
    :func:`solve`. Raises ValueError if a block is not positive definite."""
    q, _, _ = _enter(model, ws, q)
    passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
    ws.level = 0
    ws.factor_key = None                  # an integrator's factorisation is gone
    if not passes.aba_factor(ws.m, ws.w, float(c_damping), float(c_stiffness)):
        raise ValueError("factor: a joint block of the mass matrix is not positive definite "
                         "(a massless moving joint?)")


def solve(model, ws, rhs, out=None):
    """x = (M + cD D + cK K)^-1 rhs with the last :func:`factor`, O(n)."""
    rhs = np.ascontiguousarray(model.check_v(rhs, "rhs"), dtype=float)
    out = np.empty(model.nv) if out is None else out
    passes.aba_solve(ws.m, ws.w, rhs, out)
    return out


def forward_dynamics(model, ws, q, v, tau, loads=None, gravity=None):
    """Joint accelerations a with ``M a = tau - (C v + g + K (q - q0) + D v - J^T F_ext)``
    in O(n): the bias by RNEA at a = 0, then the articulated-body solve."""
    bias = rnea(model, ws, q, v, None, loads, gravity).copy()
    rhs = np.asarray(tau, dtype=float) - bias
    factor(model, ws, q)
    return solve(model, ws, rhs, ws.a)


def make_loads(model, joint, x, wrench, world):
    """LoadArrays for point wrenches: on ``joint[k]`` at abscissa ``x[k]`` of a
    soft section (-1: the joint's output frame), ``wrench[k]`` = [force;
    moment] in world axes (``world[k]``: a dead load) or body axes (follower)."""
    return LoadArrays(np.asarray(joint, np.int64).reshape(-1), np.asarray(x, float).reshape(-1),
                      np.asarray(wrench, float).reshape(-1, 6), np.asarray(world, np.bool_).reshape(-1))


def point_poses(model, ws, q, joint, x):
    """World poses (P, 4, 4) of points (joint[p], x[p]) (x: abscissa [m] in a
    soft section; -1: the joint's output frame)."""
    forward_kinematics(model, ws, q)
    joint = np.ascontiguousarray(joint, dtype=np.int64).reshape(-1)
    x = np.ascontiguousarray(x, dtype=float).reshape(-1)
    out = np.empty((len(joint), 4, 4))
    _poses(ws.m, ws.w, joint, x, out)
    return out


def point_jacobian(model, ws, q, joint, x=-1.0, frame="body"):
    """(pose 4x4, Jacobian 6 x nv) of the point (joint, x): frame "body" (its
    own axes), "world" (velocity of the point and angular velocity in world
    axes) or "spatial" (twist through the world origin)."""
    forward_kinematics(model, ws, q)
    g = np.empty((4, 4))
    Js = np.empty((6, model.nv))
    spatial_jacobian(ws.m, ws.w, int(joint), float(x), g, Js)
    if frame == "spatial":
        return g, Js
    J = Ad_inv(g) @ Js
    if frame == "body":
        return g, J
    if frame == "world":
        R = g[:3, :3]
        return g, np.vstack([R @ J[:3], R @ J[3:]])
    raise ValueError(f"frame: expected 'body', 'world' or 'spatial', got {frame!r}")


def rnea_derivatives(model, ws, q, v, a, gravity=None):
    """Analytic partial derivatives (d tau/d q, d tau/d v), each (nv, nv), of
    ``tau = M a + C v + g(q) + K (q - q0) + D v`` (gravity, no external
    loads), q moving on each joint's group (right-trivialised, as Pinocchio's
    computeRNEADerivatives); d tau/d a is M (:func:`crba`). Exponential-map
    sections only. See :mod:`kernels.derivatives`."""
    if np.any(ws.arrays.kmap != 0):
        raise NotImplementedError("rnea_derivatives: Cayley-map sections are not supported")
    q, v, a = _enter(model, ws, q, v, a)
    g = kernel_array(model.gravity if gravity is None else gravity)
    rnea(model, ws, q, v, a, None, g)
    dq = np.zeros((model.nv, model.nv))
    dv = np.zeros((model.nv, model.nv))
    rnea_derivatives_pass(ws.m, ws.w, g, q, v, a, dq, dv)
    return dq, dv


def point_jacobian_dot(model, ws, q, v, joint, x=-1.0, frame="body"):
    """Time derivative (6, nv) of :func:`point_jacobian` along (q, v), same
    frames: "spatial" ``d/dt Js``; "body" ``d/dt (Ad(g)^-1 Js) = Ad(g)^-1 (Jsdot
    - ad(Vs) Js)`` (Vs = Js v); "world" ``d/dt (blockdiag(R, R) J_body)``."""
    forward_kinematics(model, ws, q, v)
    v = np.ascontiguousarray(model.check_v(v), dtype=float)
    g = np.empty((4, 4))
    Js = np.empty((6, model.nv))
    Jsd = np.empty((6, model.nv))
    spatial_jacobian(ws.m, ws.w, int(joint), float(x), g, Js)
    spatial_jacobian_dot(ws.m, ws.w, int(joint), float(x), v, Jsd)
    if frame == "spatial":
        return Jsd
    Jbd = Ad_inv(g) @ (Jsd - ad(Js @ v) @ Js)
    if frame == "body":
        return Jbd
    if frame == "world":
        R = g[:3, :3]
        Jb = Ad_inv(g) @ Js
        Rd = R @ _hat((Jb @ v)[3:])                          # d/dt R = R hat(w_body)
        return np.vstack([Rd @ Jb[:3] + R @ Jbd[:3], Rd @ Jb[3:] + R @ Jbd[3:]])
    raise ValueError(f"frame: expected 'body', 'world' or 'spatial', got {frame!r}")


def _hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
