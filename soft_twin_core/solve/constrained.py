"""Statics and dynamics of soft articulated robots with joint control and
constraints (closed chains, boundary conditions), on the multibody engine.

Unknowns: the configuration q (statics) or the end-of-step velocity v1
(dynamics), and the multipliers lambda: one per constraint row
(:class:`mechanism.Constraint`) and one per position-controlled joint.

* A constraint's multipliers are its reaction: the world wrench
  ``W = C^T lambda`` on frame a at a's origin, and -W on frame b. They enter
  the equations as dead point loads, so the engine's RNEA gives their
  generalised force ``G^T lambda`` (G = C (J_a - J_b), J the world-axes point
  Jacobians) and its static tangent includes d(G^T lambda)/dq at fixed W.
* A position-controlled joint j has the row ``q_j - q_cmd = 0``; its
  multiplier is the joint's effort (inverse dynamics, N m or N).

Statics solves ``R(q) - G^T lambda = 0, Phi(q) = 0`` by Newton on the KKT
system ``[[Kt, -G^T], [G, 0]]`` (Kt: the engine's analytic tangent). Dynamics
takes the integrator's theta-method step (:mod:`integrators`) with the
constraint forces at the intermediate state and ``Phi(q1) = 0`` at the end
of the step (position level, no drift beyond the Newton tolerance); the
Newton matrix is ``[[ (M + th h D + (th h)^2 Kt)/h, -G_t^T ], [th h G_1, 0]]``,
dense (these mechanisms have tens to hundreds of dof).

Rotation rows of a clamp use ``log(R_a R_b^T)`` whose derivative is
``w_a - w_b`` at zero error: Newton's matrix is exact at the solution.
"""

import contextlib
from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from soft_twin_core._blas import one_blas_thread
from soft_twin_core.engine import step_matrix
from soft_twin_core.engine.algorithms import crba, forward_kinematics, point_poses
from soft_twin_core.engine.contact import ContactPoints, ContactState, moved
from soft_twin_core.engine.closed_step import CLAMPED, ClosedArrays, closed_step
from soft_twin_core.engine.contact_step import contact_step
from soft_twin_core.engine.forces import (actuation_tangent_pass, actuator_arrays, check_member_loads,
                                          concat_loads, gravity_of, load_arrays, point_moment_arrays,
                                          tendon_coefficients)
from soft_twin_core.engine.integrators import ThetaIntegrator, integrate_pass, residual_pass
from soft_twin_core.engine.reduced_step import ReducedThetaIntegrator
from soft_twin_core.engine.joint_kinds import FREE, PRISMATIC, REVOLUTE, SPHERICAL
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import LoadArrays, kernel_array
from soft_twin_core.engine.kernels.contact import obstacle_arrays, posable
from soft_twin_core.engine.kernels.frames import world_point_jacobians
from soft_twin_core.solve.contact import MemberContact
from soft_twin_core.engine.kernels.tangent import static_tangent_pass
from soft_twin_core.engine.loads import Loads
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError, StepError
from soft_twin_core.lie import exp_se3, log_se3, log_so3, se3_inv
from soft_twin_core.solve import equilibrium as eq
from soft_twin_core.solve.equilibrium import equilibrium_stability

# The compiled steps' stopping rule, run from its Python source in the Python step (one rule)
forces_balanced = step_matrix.forces_balanced.py_func
update_converged = step_matrix.update_converged.py_func

FrameLoad = namedtuple("FrameLoad", ["frame", "wrench", "axes"])
FrameLoad.__doc__ = """A point wrench [fx, fy, fz, mx, my, mz] (N, N m) on a named frame of a
mechanism, in ``axes`` "world" (dead load) or "body" (follower)."""
FrameLoad.__new__.__defaults__ = ("world",)


# ----------------------------------------------------------------------------
# Inputs, checked once
# ----------------------------------------------------------------------------

@dataclass
class Inputs:
    """Checked inputs of a mechanism: actuation u (n_actuators,), efforts of
    effort-controlled joints (nv,) [N m or N], position commands of the
    position-controlled joints (n_pos,) [rad or m] (with velocity and
    acceleration for dynamics; ``v_cmd`` None: not given), loads on paths and frames."""
    u: np.ndarray
    effort: np.ndarray
    q_cmd: np.ndarray
    v_cmd: np.ndarray
    loads: LoadArrays
    gravity: np.ndarray


def actuation_vector(model, actuation):
    """Inputs (n_actuators,) from a dict {name: value}, a sequence, or None.
    Tendon tensions must be >= 0 N; every value finite."""
    n = len(model.actuators)
    if actuation is None:
        return np.zeros(n)
    if isinstance(actuation, dict):
        u = np.zeros(n)
        names = model.actuator_names
        for k, v in actuation.items():
            if k not in names:
                raise ValueError(f"actuation: unknown actuator {k!r}; this robot has {list(names)}")
            try:
                u[names.index(k)] = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"actuation: {k} = {v!r} is not a number") from None
    else:
        try:
            u = np.asarray(actuation, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"actuation: expected {n} numbers, got {actuation!r}") from None
        if u.shape != (n,):
            raise ValueError(f"actuation: expected {n} values (one per actuator {list(model.actuator_names)}), "
                             f"got shape {u.shape}")
    for a, val in zip(model.actuators, u):
        if not np.isfinite(val):
            raise ValueError(f"actuation: {a.name} = {val} is not finite")
        if a.kind == "tendon" and val < 0:
            raise ValueError(f"actuation: tendon {a.name} tension must be >= 0 N, got {val}")
    return u


def joint_vector(mech, values, mode, what, unit):
    """Values (by joint name) of the joints of control ``mode`` -> array in the
    order of ``mech.joints_with(mode)``; unknown names, NaN and positions
    outside the limits raise ValueError naming the joint."""
    idx = mech.joints_with(mode)
    names = [mech.tree.joints[i].name for i in idx]
    out = np.array([mech.tree.joints[i].q_ref for i in idx]) if what == "position" else np.zeros(len(idx))
    if values is None:
        return out
    if not isinstance(values, dict):
        v = np.asarray(values, dtype=float)
        if v.shape != (len(idx),):
            raise ValueError(f"{what}: expected {len(idx)} values (joints {names}), got shape {v.shape}")
        values = dict(zip(names, v))
    for k, v in values.items():
        if k not in names:
            allj = [j.name for j in mech.tree.joints if j.kind in (REVOLUTE, PRISMATIC)]
            why = (f"joint {k!r} is not {mode}-controlled" if k in allj else f"unknown joint {k!r}")
            raise ValueError(f"{what}: {why}; the {mode}-controlled joints are {names}")
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise ValueError(f"{what}: {k} = {v!r} is not a number") from None
        if not np.isfinite(v):
            raise ValueError(f"{what}: {k} = {v} is not finite")
        j = mech.tree.joints[idx[names.index(k)]]
        if what == "position" and j.limits is not None and not j.limits[0] <= v <= j.limits[1]:
            raise ValueError(f"{what}: {k} = {v} {unit} lies outside the joint limits {list(j.limits)}")
        out[names.index(k)] = v
    return out


def frame_loads(mech, point_loads):
    """LoadArrays of FrameLoads (ValueError naming an unknown frame or a bad wrench)."""
    J, X, W, F = [], [], [], []
    for k, pl in enumerate(point_loads):
        fl = pl if isinstance(pl, FrameLoad) else FrameLoad(*pl)
        try:
            ref = mech.frame(fl.frame)
        except KeyError as e:
            raise ValueError(f"point_loads[{k}].frame: {e.args[0]}") from None
        w = np.asarray(fl.wrench, dtype=float)
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ValueError(f"point_loads[{k}].wrench: expected 6 finite numbers [f; m], got {fl.wrench!r}")
        if fl.axes not in ("world", "body"):
            raise ValueError(f"point_loads[{k}].axes: expected 'world' or 'body', got {fl.axes!r}")
        J.append(ref.joint)
        X.append(ref.x)
        W.append(w)
        F.append(fl.axes == "world")
    return LoadArrays(np.array(J, np.int64), np.array(X, float), np.array(W, float).reshape(-1, 6),
                      np.array(F, np.bool_))


def make_inputs(mech, actuation=None, efforts=None, positions=None, velocities=None, loads=None,
                point_loads=(), path=None):
    """Check every input of a mechanism once (ValueError naming the bad one)."""
    tree = mech.tree
    u = actuation_vector(mech, actuation)
    eff = joint_vector(mech, efforts, "effort", "effort", "N m or N")
    effort = np.zeros(tree.nv)
    for k, i in enumerate(mech.joints_with("effort")):
        effort[tree.idx_v[i]] = eff[k]
    q_cmd = joint_vector(mech, positions, "position", "position", "rad or m")
    v_cmd = None
    if velocities is not None:
        v_cmd = joint_vector(mech, velocities, "position", "velocity", "rad/s or m/s") if isinstance(
            velocities, dict) else np.asarray(velocities, float)
        if v_cmd.shape != q_cmd.shape or not np.all(np.isfinite(v_cmd)):
            raise ValueError(f"velocities: expected {len(q_cmd)} finite values (the position-controlled joints)")
    loads = Loads() if loads is None else loads
    check_member_loads(tree, loads)
    ld = concat_loads(load_arrays(tree, loads, u, path) if tree.paths else   # with point-moment tendons at u
                       frame_loads(mech, ()), frame_loads(mech, point_loads))
    return Inputs(u, effort, q_cmd, v_cmd, ld, gravity_of(tree, loads))


def assemble_inputs(mech, u, efforts, positions, velocities=None, point_loads=()):
    """:class:`Inputs` of values checked at the door (the node's parse
    functions, :func:`make_inputs`), without checking them again: ``u``
    (n_actuators,), ``efforts`` and ``positions`` {joint: value} of the
    effort- and position-controlled joints (the others at 0 and at their
    reference), ``velocities`` {joint: value} or None, ``point_loads``
    (FrameLoad on existing frames), the point-moment tendons' follower
    moments at u. Gravity on, no path loads."""
    tree = mech.tree
    effort = np.zeros(tree.nv)
    for i in mech.joints_with("effort"):
        effort[tree.idx_v[i]] = efforts.get(tree.joints[i].name, 0.0)
    pos = mech.joints_with("position")
    q_cmd = np.array([positions.get(tree.joints[i].name, tree.joints[i].q_ref) for i in pos], dtype=float)
    v_cmd = None if velocities is None else np.array([velocities.get(tree.joints[i].name, 0.0) for i in pos],
                                                     dtype=float)
    u = np.asarray(u, dtype=float)
    return Inputs(u, effort, q_cmd, v_cmd, concat_loads(_checked_frame_loads(mech, point_loads),
                                                         point_moment_arrays(tree, u)),
                  kernel_array(tree.gravity))


def _checked_frame_loads(mech, point_loads):
    if not point_loads:
        return LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))
    return frame_loads(mech, point_loads)


# ----------------------------------------------------------------------------
# Constraint rows
# ----------------------------------------------------------------------------

def _constraint_points(mech):
    """(joint, x) arrays of the constraints' frames a and b, in order (cached)."""
    pts = mech.__dict__.get("_constraint_points")
    if pts is None:
        refs = [r for c in mech.constraints for r in (c.a, c.b)]
        pts = (np.array([r.joint for r in refs], np.int64), np.array([r.x for r in refs], float))
        object.__setattr__(mech, "_constraint_points", pts)
    return pts


def constraint_rows(mech, ws, q, targets=None, q_cmd=None):
    """(Phi (m,), G (m, nv)) of all constraints and motion rows at q:
    constraint values in world axes [m, rad] and their Jacobian (exact for
    positions, and for rotations at zero error). ``targets``: world target
    poses of the constraints to the world (default their own)."""
    tree = mech.tree
    blocks_phi, blocks_G = [], []
    if mech.constraints:
        joint, x = _constraint_points(mech)
        g = np.empty((len(joint), 4, 4))
        J = np.empty((len(joint), 6, tree.nv))
        passes.forward_pass(ws.m, ws.w, np.ascontiguousarray(q, float), ws.zeros_v, ws.zeros_v, 0)
        world_point_jacobians(ws.m, ws.w, joint, x, g, J)
    for k, c in enumerate(mech.constraints):
        ga, Ja = g[2 * k], J[2 * k]
        if c.b.joint < 0:
            gb = c.target if targets is None or targets[k] is None else targets[k]
            Jb = J[2 * k + 1]                  # zeros
        else:
            gb, Jb = g[2 * k + 1], J[2 * k + 1]
        dp = ga[:3, 3] - gb[:3, 3]
        Jd = Ja - Jb
        C = c.rows()
        if c.kind == "clamped":
            blocks_phi.append(np.concatenate([dp, log_so3(ga[:3, :3] @ gb[:3, :3].T)]))
            blocks_G.append(Jd)
        else:
            blocks_phi.append(C[:, :3] @ dp)
            blocks_G.append(C @ Jd)
    pos = mech.joints_with("position")
    if pos:
        E = np.zeros((len(pos), tree.nv))
        phi = np.zeros(len(pos))
        for k, i in enumerate(pos):
            E[k, tree.idx_v[i]] = 1.0
            phi[k] = q[tree.idx_q[i]] - (q_cmd[k] if q_cmd is not None else tree.joints[i].q_ref)
        blocks_phi.append(phi)
        blocks_G.append(E)
    if not blocks_phi:
        return np.zeros(0), np.zeros((0, tree.nv))
    return np.concatenate(blocks_phi), np.vstack(blocks_G)


def constraint_loads(mech, lam):
    """LoadArrays of the constraint reactions: C^T lambda on a, its opposite on b
    (dead world wrenches at the frames' origins)."""
    J, X, W = [], [], []
    r = 0
    for c in mech.constraints:
        w = c.rows().T @ lam[r:r + c.size]
        r += c.size
        J.append(c.a.joint)
        X.append(c.a.x)
        W.append(w)
        if c.b.joint >= 0:
            J.append(c.b.joint)
            X.append(c.b.x)
            W.append(-w)
    return LoadArrays(np.array(J, np.int64), np.array(X, float), np.array(W, float).reshape(-1, 6),
                      np.ones(len(J), np.bool_))


def constraint_wrenches(mech, lam):
    """{name: world wrench [f; m] (6,) the constraint exerts on its frame a, at a's origin}."""
    out, r = {}, 0
    for c in mech.constraints:
        out[c.name] = c.rows().T @ lam[r:r + c.size]
        r += c.size
    return out


def _efforts_out(mech, lam, inp):
    """{joint name: effort} of the 1-dof rigid joints: inputs of the
    effort-controlled, multipliers of the position-controlled, 0 passive."""
    tree = mech.tree
    out = {}
    npos = len(mech.joints_with("position"))
    lam_pos = lam[len(lam) - npos:] if npos else np.zeros(0)
    pos = mech.joints_with("position")
    for i in mech.rigid_joints:
        j = tree.joints[i]
        if i in pos:
            out[j.name] = float(lam_pos[pos.index(i)])
        else:
            out[j.name] = float(inp.effort[tree.idx_v[i]])
    return out


# ----------------------------------------------------------------------------
# The equilibrium problem
# ----------------------------------------------------------------------------

def dense_stiffness_damping(tree):
    """Joint-space stiffness and damping matrices (nv, nv) of the tree (its
    joints' blocks and its elastic fields')."""
    K = np.zeros((tree.nv, tree.nv))
    D = np.zeros((tree.nv, tree.nv))
    a = tree.arrays
    for i in range(tree.n_joints):
        n, iv = a.nv[i], a.iv[i]
        K[iv:iv + n, iv:iv + n] = a.Kb[i, :n, :n]
        D[iv:iv + n, iv:iv + n] = a.Db[i, :n, :n]
    rows = np.ix_(a.ef_v, a.ef_v)          # the elastic fields' (multibody.ElasticField)
    K[rows] += a.ef_P.T @ a.ef_K @ a.ef_P
    D[rows] += a.ef_P.T @ a.ef_D @ a.ef_P
    return K, D


def _cached(mech, key, make):
    v = mech.__dict__.get(key)
    if v is None:
        v = make()
        object.__setattr__(mech, key, v)
    return v


class _Equilibrium:
    """R(q, lambda) and Phi(q) of a mechanism under fixed inputs, with the
    analytic Newton matrix. With variable-strain segments (``T`` the
    mechanism's strain basis) the Newton unknowns are their coordinates:
    the residual ``T^T R``, the constraint Jacobian ``G T``, the tangent
    ``T^T Kt T``, and :meth:`lift` maps an update back to q."""

    def __init__(self, mech, inp, targets=None, obstacles=None, stick=None):
        self.mech, self.inp, self.targets, self.stick = mech, inp, targets, stick
        self.contact = MemberContact(mech, obstacles)
        tree = mech.tree
        self.tree = tree
        self.ws = Workspace(tree)
        self.act = _cached(mech, "_act_arrays", lambda: actuator_arrays(tree))
        self.K, _ = _cached(mech, "_dense_KD", lambda: dense_stiffness_damping(tree))
        self.coef = tendon_coefficients(self.act, inp.u)
        self.zeros = np.zeros(tree.nv)
        self.npos = len(mech.joints_with("position"))
        self.pos_v = np.array([tree.idx_v[i] for i in mech.joints_with("position")], dtype=np.int64)
        self.T = mech.basis

    def lift(self, dz):
        """The update of q of a Newton update of the unknowns."""
        return dz if self.T is None else self.T @ dz

    def loads(self, lam, contact=None):
        """The loads at multipliers lam (and contacts ``contact``, a ContactState)."""
        out = concat_loads(self.inp.loads, constraint_loads(self.mech, lam))
        return out if contact is None else concat_loads(out, self.contact.loads(contact))

    def contacts(self, q):
        """The ContactState at q (None without obstacles)."""
        return self.contact.state(self.ws, q, self.stick) if self.contact else None

    def effort(self, lam):
        e = self.inp.effort.copy()
        if self.npos:
            e[self.pos_v] += lam[len(lam) - self.npos:]
        return e

    def residual(self, q, lam):
        out = np.empty(self.tree.nv)
        residual_pass(self.ws.m, self.ws.w, self.act, self.loads(lam, self.contacts(q)), self.inp.gravity, self.coef,
                      self.effort(lam), np.ascontiguousarray(q, float), self.zeros, self.zeros, out, True)
        phi, G = constraint_rows(self.mech, self.ws, q, self.targets, self.inp.q_cmd)
        if self.T is not None:
            return self.T.T @ out, phi, G @ self.T
        return out, phi, G

    def tangent(self, q, lam):
        m, w = self.ws.m, self.ws.w
        q = np.ascontiguousarray(q, float)
        st = self.contacts(q)
        ld = self.loads(lam, st)
        passes.forward_pass(m, w, q, self.zeros, self.zeros, 0)
        passes.rnea_pass(m, w, ld, self.inp.gravity, np.empty(self.tree.nv), True)
        Kt = self.K.copy()
        static_tangent_pass(m, w, ld, self.inp.gravity, Kt)
        actuation_tangent_pass(m, w, self.act, self.coef, Kt)
        if st is not None:
            self.contact.add_stiffness(self.ws, st, Kt)
        return Kt if self.T is None else self.T.T @ Kt @ self.T


@dataclass
class Equilibrium:
    """A static equilibrium of a mechanism: q; multipliers lam; joint_efforts
    {name: N m or N}; constraint_wrenches {name: world [f; m] on frame a};
    iterations; residual (relative); constraint_error (max |Phi|, m or rad);
    stable and :attr:`min_stiffness_eigenvalue` (see
    :func:`equilibrium_stability`)."""
    q: np.ndarray
    lam: np.ndarray
    joint_efforts: dict
    constraint_wrenches: dict
    iterations: int
    residual: float
    constraint_error: float
    load_steps: int = 1
    inputs: Inputs = None
    stable: bool = True                 # see equilibrium_stability
    lowest_eigenvalue: float = float("nan")     # when the solve computed it (else: min_stiffness_eigenvalue)
    tangent: object = None              # without constraints: the last Newton tangent (a tangent_hint)
    stability_tangent: object = None    # the tangent the stability was judged on, if its eigenvalue is not known
    contacts: object = None             # with obstacles: the engine.contact.ContactState at q

    @property
    def min_stiffness_eigenvalue(self):
        """The smallest eigenvalue of the (reduced) stiffness, nan when the
        stability was not judged; without constraints it is computed at
        first use (an O(n^3) eigen-solve the solve itself does without: a
        Cholesky factorisation decides the stability)."""
        if np.isnan(self.lowest_eigenvalue) and self.stability_tangent is not None:
            self.lowest_eigenvalue = equilibrium_stability(self.stability_tangent)[1]
        return self.lowest_eigenvalue


def independent_rows(G, rtol=1e-10):
    """Indices of a maximal set of linearly independent rows of G (QR with
    column pivoting of G^T): redundant constraints (a planar loop closed by
    a 3-D pin) are left out; their multipliers stay as they are."""
    from scipy.linalg import qr
    if G.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    Gs = G / np.maximum(np.abs(G).max(axis=1, keepdims=True), 1e-300)
    _, Rq, piv = qr(Gs.T, mode="economic", pivoting=True)
    d = np.abs(np.diag(Rq))
    r = int(np.sum(d > rtol * max(d.max(initial=0.0), 1e-300)))
    return np.sort(piv[:r])


def factor_kkt(A, G_force, G_cons, rows=None):
    """LU factors of ``[[A, -G_force^T], [G_cons, 0]]`` over the independent
    rows of G_cons (``rows``: those rows if known), for :func:`solve_factored`."""
    import warnings
    from scipy.linalg import LinAlgWarning, lu_factor
    n = A.shape[0]
    rows = independent_rows(G_cons) if rows is None else rows
    m = len(rows)
    K = np.zeros((n + m, n + m))
    K[:n, :n] = A
    K[:n, n:] = -G_force[rows].T
    K[n:, :n] = G_cons[rows]
    with warnings.catch_warnings():     # a singular matrix is reported below, as an error the caller words
        warnings.simplefilter("ignore", LinAlgWarning)
        lu = lu_factor(K, check_finite=False)
    if not np.all(np.isfinite(lu[0])) or np.min(np.abs(np.diag(lu[0])), initial=np.inf) == 0.0:
        raise np.linalg.LinAlgError("singular Newton matrix")
    return lu, rows, n, G_cons.shape[0]


def solve_factored(fac, R, phi):
    """(dx, dlam) of the system of :func:`factor_kkt` for the right-hand side
    [-R; -phi] (dlam = 0 on redundant rows); R and phi may be matrices (one
    right-hand side a column)."""
    from scipy.linalg import lu_solve
    lu, rows, n, mall = fac
    x = lu_solve(lu, -np.concatenate([R, phi[rows]]), check_finite=False)
    dl = np.zeros((mall,) + x.shape[1:])
    dl[rows] = x[n:]
    return x[:n], dl


def solve_kkt(A, G_force, G_cons, R, phi, rows=None):
    """(dx, dlam) of ``[[A, -G_force^T], [G_cons, 0]] [dx; dlam] = [-R; -phi]``
    over the independent rows of G_cons (dlam = 0 on the redundant ones;
    ``rows``: those rows if known)."""
    return solve_factored(factor_kkt(A, G_force, G_cons, rows), R, phi)


def _check_statics_model(mech, obstacles):
    """ValueError, in the robot file's words, for what statics cannot hold:
    a floating base, spherical or free joints with nothing to hold them. A
    prescribed base is held where its clamp puts it (:func:`carry_base`):
    its free joint is never moved by the Newton (the clamp holds it
    exactly from the first iterate). A loose object (a free or spherical
    joint) is held by contacts (a gripper's fingers, a table): statics
    takes it when the robot has obstacles or shapes, and moves it by the
    group's exponential (:func:`_moved_by`); with friction it needs stick
    points where it touches (:class:`solve.contact.StickPoints`: a twin or
    a scenario's load steps keep them), else it slides off (no
    equilibrium: StaticsError)."""
    tree = mech.tree
    motion = getattr(mech, "base_motion", "fixed")
    if motion == "floating":
        raise ValueError("statics: the base is floating (base.motion: floating): a free body has no static "
                         "equilibrium under gravity unless held; clamp it (base.motion: fixed) or run the "
                         "dynamics to let it settle")
    if obstacles or mech.shapes:
        return
    loose = _loose_joints(mech)
    if loose:
        name = loose[0]
        kind = "spherical" if tree.joints[tree.joint_index(name)].kind == SPHERICAL else "free"
        raise ValueError(f"statics: joint {name!r} is {kind} and nothing can hold it (no obstacle, no collision "
                         f"shape): statics needs joints with nq = nv (soft, revolute, prismatic, fixed) or a loose "
                         f"object held by contacts; use the dynamics to let it settle")


def _loose_joints(mech):
    """Names of the free and spherical joints statics moves (not a carried base's)."""
    carried = _carried_base(mech)
    return [j.name for i, j in enumerate(mech.tree.joints)
            if j.kind in (SPHERICAL, FREE) and (carried is None or i != carried[0])]


def _carried_base(mech):
    """(joint, q offset, v offset, constraint index) of a prescribed base's
    free joint (held by the clamp named 'base'), or None."""
    if getattr(mech, "base_motion", "fixed") != "prescribed":
        return None
    for k, c in enumerate(mech.constraints):
        if c.name == "base" and mech.tree.joints[c.a.joint].kind == FREE:
            j = c.a.joint
            return j, mech.tree.idx_q[j], mech.tree.idx_v[j], k
    return None


def _free_coordinates(g):
    """A free joint's coordinates (position, unit quaternion x y z w) of the
    4x4 ``g``: :func:`_free_pose`'s inverse (Shepperd's method: the largest
    of w, x, y, z first, so no division by a small number)."""
    R = g[:3, :3]
    tr = np.trace(R)
    k = int(np.argmax([tr, R[0, 0], R[1, 1], R[2, 2]]))
    if k == 0:
        w = 0.5 * np.sqrt(1.0 + tr)
        x, y, z = (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)
    elif k == 1:
        x = 0.5 * np.sqrt(1.0 + 2 * R[0, 0] - tr)
        w, y, z = (R[2, 1] - R[1, 2]) / (4 * x), (R[0, 1] + R[1, 0]) / (4 * x), (R[0, 2] + R[2, 0]) / (4 * x)
    elif k == 2:
        y = 0.5 * np.sqrt(1.0 + 2 * R[1, 1] - tr)
        w, x, z = (R[0, 2] - R[2, 0]) / (4 * y), (R[0, 1] + R[1, 0]) / (4 * y), (R[1, 2] + R[2, 1]) / (4 * y)
    else:
        z = 0.5 * np.sqrt(1.0 + 2 * R[2, 2] - tr)
        w, x, y = (R[1, 0] - R[0, 1]) / (4 * z), (R[0, 2] + R[2, 0]) / (4 * z), (R[1, 2] + R[2, 1]) / (4 * z)
    quat = np.array([x, y, z, w])
    return np.concatenate([g[:3, 3], quat / np.linalg.norm(quat)])


def carry_base(mech, q, targets=None):
    """q with a prescribed base's free joint where the clamp 'base' puts the
    base frame: at its target in ``targets`` (:func:`base_targets`), else
    at the robot file's base pose (a copy; q itself without a prescribed
    base). The base frame is the free joint's output frame, so its pose is
    the joint's placement times the joint's transform."""
    carried = _carried_base(mech)
    if carried is None:
        return q
    j, iq, _, k = carried
    T = targets[k] if targets is not None and targets[k] is not None else mech.constraints[k].target
    q = np.array(q, dtype=float)
    q[iq:iq + 7] = _free_coordinates(se3_inv(mech.tree.joints[j].placement) @ T)
    return q


def _base_path(mech, q_start, targets):
    """The constraints' targets as a function of the load fraction t in
    [0, 1] (the continuation's): a prescribed base carried along the
    geodesic ``T0 exp(t log(T0^-1 T1))`` from where it is at ``q_start``
    to its target T1, so that a base posed far from where the robot rests
    is brought there in steps, as the loads are; the other targets as
    given."""
    carried = _carried_base(mech)
    if carried is None:
        return lambda t: targets
    j, iq, _, k = carried
    T1 = targets[k] if targets is not None and targets[k] is not None else mech.constraints[k].target
    T0 = mech.tree.joints[j].placement @ _free_pose(q_start[iq:iq + 7])
    X = log_se3(se3_inv(T0) @ T1)

    def at(t):
        out = list(targets) if targets is not None else [None] * len(mech.constraints)
        out[k] = T0 @ exp_se3(t * X)
        return out
    at.carries = bool(np.abs(X).max() > 0)
    return at


def _coordinate_offsets(tree, q):
    """q - q0 per velocity coordinate (nv), zero on group joints (spherical,
    free: they carry no spring): what the stiffness matrix multiplies."""
    if tree.nq == tree.nv:
        return q - tree.q0
    out = np.zeros(tree.nv)
    for i, j in enumerate(tree.joints):
        if j.kind not in (SPHERICAL, FREE):
            a, b = tree.idx_q[i], tree.idx_v[i]
            out[b:b + j.nv] = q[a:a + j.nv] - tree.q0[a:a + j.nv]
    return out


def _moved_by(ws, q, dq, step):
    """q (+) step dq: addition, and the group exponential on a prescribed
    base's free joint (:func:`integrators.integrate_pass`)."""
    if q.shape == dq.shape:
        return q + step * dq
    out = np.empty_like(q)
    integrate_pass(ws.m, np.ascontiguousarray(q), np.ascontiguousarray(dq), step, out)
    return out


def _free_pose(q):
    """The 4x4 of a free joint's coordinates (position, unit quaternion x y
    z w; scipy's Rotation would import scipy.linalg at start-up)."""
    x, y, z, w = q[3:7]
    g = np.eye(4)
    g[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    g[:3, 3] = q[:3]
    return g


def _length_scale(mech):
    L = sum(p.length for p in mech.tree.paths)
    return max(L, 1e-3)


def gap_force_scale(k_max, phi, length):
    """The generalised force it takes to close the constraint violation
    ``phi`` [m, rad] of a chain of length ``length``: the largest stiffness
    times the strain the gap implies, ``k_max |phi|_max / length``. A scale
    for the residuals that is not zero when nothing is loaded but a chain is
    open (an unloaded closed chain with a 1 mm gap had a scale of 1e-300 and
    its merit function overflowed)."""
    return k_max * np.abs(phi).max(initial=0) / length


STALL_STEP, STALL_ITERATIONS = 1.0 / 32, 4     # Newton stalls: this many steps in a row cut to this or less


def _kkt_newton(pb, q, lam, tol, max_iterations, stall=False):
    """Newton with backtracking on the KKT system; (q, lam, it, ok, R, phi).
    ``stall``: give up early when it stalls (``STALL_ITERATIONS`` steps in
    a row cut to ``STALL_STEP`` or less: a linear model far from the
    solution, e.g. an arm falling onto a table from straight, whose Newton
    step goes metres through it), so that the caller's continuation takes
    over instead of 50 creeping iterations (:func:`solve_equilibrium` from
    the reference configuration); else it creeps on (a catheter sliding
    round a bend converges so, in 30-46 iterations a step)."""
    Ls = _length_scale(pb.mech)
    R, phi, G = pb.residual(q, lam)
    Kq = pb.K @ _coordinate_offsets(pb.tree, q)
    k_max = np.abs(pb.K).max(initial=0)

    def scale_of(R):
        return max(np.abs(Kq).max(initial=0), np.abs(R).max(initial=0), np.abs(pb.inp.effort).max(initial=0),
                   np.abs(lam).max(initial=0) * Ls, gap_force_scale(k_max, phi, Ls), 1e-300)

    def merit(R, phi, sc):
        return np.sqrt(np.sum((R / sc) ** 2) + np.sum((phi / Ls) ** 2))

    sc = scale_of(R)
    stalled = 0
    for it in range(1, max_iterations + 1):
        r_ok = np.abs(R).max(initial=0) <= tol * sc + 64 * np.finfo(float).eps * np.abs(Kq).max(initial=0)
        if r_ok and np.abs(phi).max(initial=0) <= tol * Ls:
            return q, lam, it - 1, True, R, phi, sc
        Kt = pb.tangent(q, lam)
        try:
            dq, dl = solve_kkt(Kt, G, G, R, phi)
        except np.linalg.LinAlgError:
            return q, lam, it, False, R, phi, sc
        f0 = merit(R, phi, sc)
        step = 1.0
        for _ in range(30):
            q_t, l_t = _moved_by(pb.ws, q, pb.lift(dq), step), lam + step * dl
            R_t, phi_t, G_t = pb.residual(q_t, l_t)
            if np.all(np.isfinite(R_t)) and merit(R_t, phi_t, sc) < (1 - 1e-4 * step) * f0:
                break
            step *= 0.5
        else:
            return q, lam, it, False, R, phi, sc
        stalled = stalled + 1 if step <= STALL_STEP else 0
        if stall and stalled >= STALL_ITERATIONS:
            return q, lam, it, False, R, phi, sc
        q, lam, R, phi, G = q_t, l_t, R_t, phi_t, G_t
        Kq = pb.K @ _coordinate_offsets(pb.tree, q)
        sc = max(sc, scale_of(R))
    return q, lam, max_iterations, False, R, phi, sc


def solve_equilibrium(mech, actuation=None, efforts=None, positions=None, loads=None, point_loads=(),
                      q_init=None, *, targets=None, tol=1e-10, max_iterations=50, max_load_steps=64,
                      check_stability=True, tangent_hint=None, inputs=None, obstacles=None, stick=None):
    """Static equilibrium of a mechanism under actuation (tendon tensions N,
    chamber pressures Pa), joint efforts {joint: N m or N} of effort-controlled
    joints, positions {joint: rad or m} of position-controlled joints (default
    their reference), loads (:class:`loads.Loads` on the first path, gravity
    switch) and point_loads (FrameLoad on named frames); constraints hold.
    If Newton fails from q_init, the inputs are applied in increasing
    fractions (continuation). Raises StaticsError if it cannot converge.
    ``check_stability``: judge the equilibrium found (``stable``,
    ``min_stiffness_eigenvalue``: :func:`equilibrium_stability`); an
    unstable one is returned, flagged (a column past its buckling load
    still has its straight equilibrium). A mechanism without constraint
    rows or position-controlled joints (a classic rod, a tree of soft
    members and effort-controlled or passive joints) is solved by
    :func:`equilibrium.solve`: compiled Newton, the loaded path preferred
    to an unstable equilibrium, and ``tangent_hint`` (a previous result's
    ``tangent``) to skip the first tangents. ``inputs``: :class:`Inputs`
    already checked (:func:`make_inputs`, :func:`assemble_inputs`) instead
    of the input arguments. ``obstacles`` (default the robot file's): what
    the soft members touch (:mod:`soft_twin_core.solve.contact`); with
    any, the contacts found are ``contacts`` (a ContactState) and the
    solve is the KKT Newton's, with the contacts' stiffness in its matrix.
    ``stick`` (:class:`solve.contact.StickPoints`, where the contact points
    stick: an earlier equilibrium's, :meth:`MemberContact.stuck_after`):
    the world obstacles' friction acts against the contacts' displacements
    from there (:func:`engine.contact.stick_friction`); None: statics
    without friction."""
    obstacles = tuple(mech.obstacles if obstacles is None else obstacles)
    _check_statics_model(mech, obstacles)
    inp = inputs if inputs is not None else make_inputs(mech, actuation, efforts, positions, None, loads, point_loads)
    tree = mech.tree
    q_start = tree.q0.copy() if q_init is None else tree.check_q(np.array(q_init, dtype=float), "q_init").copy()
    if mech.basis is not None:            # variable-strain segments: the start on their basis (least squares)
        q_start = onto_basis(mech, q_start)
    q = carry_base(mech, q_start, targets)
    m = mech.n_constraint_rows + len(mech.joints_with("position"))
    lam = np.zeros(m)
    if m == 0 and not obstacles and not mech.shapes:       # (shapes: the robot's own, which members touch)
        return _free_equilibrium(mech, inp, q, tol, max_iterations, max_load_steps, check_stability, tangent_hint)
    with one_blas_thread():
        pb = _Equilibrium(mech, inp, targets, obstacles, stick)
        # from the reference configuration, a stalled Newton gives up for the continuation; from a warm start
        # (a twin's last shape, the step before on a path) it creeps on: scaling the loads from there changes
        # what friction holds (a catheter sliding round a bend)
        q1, lam1, it, ok, R, phi, sc = _kkt_newton(pb, q, lam, tol, max_iterations, stall=q_init is None)
        steps, total = 1, it
        if not ok:
            try:
                q1, lam1, total, steps, R, phi, sc = _continuation(mech, inp, _base_path(mech, q_start, targets),
                                                                   q_start, lam, tol, max_iterations, max_load_steps,
                                                                   total, obstacles, stick)
            except StaticsError as e:
                loose = _loose_joints(mech)
                if loose and stick is None:
                    raise StaticsError(f"{e}; the loose object(s) {loose} can be held only by friction, which "
                                       f"statics gives from stick points (stick=MemberContact.stuck_at(...): the "
                                       f"quasi-static twin and a scenario's statics keep them)") from e
                raise
        stable, lo = True, float("nan")
        pb = _Equilibrium(mech, inp, targets, obstacles, stick)
        if check_stability:
            _, _, G = pb.residual(q1, lam1)
            stable, lo = equilibrium_stability(pb.tangent(q1, lam1), G)
    return Equilibrium(q1.copy(), lam1.copy(), _efforts_out(mech, lam1, inp), constraint_wrenches(mech, lam1),
                       total, float(np.abs(R).max(initial=0) / sc), float(np.abs(phi).max(initial=0)), steps,
                       inp, stable, lo, contacts=pb.contacts(q1))


def on_basis(mech, dq, name):
    """The coordinates z of ``dq`` (a velocity, or :func:`basis_offset` of
    a configuration) on the robot's strain basis (``dq = B z``); ValueError
    naming ``name`` when dq is not on it (a configuration the
    variable-strain segments cannot take)."""
    B = mech.basis
    z = np.linalg.lstsq(B, dq, rcond=None)[0]
    off = np.abs(B @ z - dq).max(initial=0.0)
    if off > 1e-9 * max(1.0, np.abs(dq).max(initial=0.0)):
        raise ValueError(f"{name}: not a configuration of the robot's variable-strain segments (off their strain "
                         f"basis by {off:.3g}); start from the basis's coordinates: q = q0 + B z "
                         f"(Mechanism.basis)")
    return z


def basis_offset(mech, q):
    """What must lie on the strain basis of a configuration q:
    :func:`_coordinate_offsets` (q - q0 on the coordinates that add, zero
    on the quaternion joints', which move on their groups and are identity
    columns of the basis of their own)."""
    return _coordinate_offsets(mech.tree, q)


def basis_coordinates(mech, q):
    """The coordinates z (nz,) of q on the robot's strain basis (variable-
    strain segments: ``q = q0 + B z``, least squares; their names are
    ``mech.coordinate_names``), or None when it has none."""
    if mech.basis is None:
        return None
    return np.linalg.lstsq(mech.basis, basis_offset(mech, q), rcond=None)[0]


def onto_basis(mech, q):
    """q with its additive coordinates moved to the nearest configuration
    of the strain basis (least squares), the quaternions kept."""
    tree = mech.tree
    change = mech.basis @ basis_coordinates(mech, q) - basis_offset(mech, q)   # zero on the quaternion joints
    out = np.array(q, dtype=float)
    for i, j in enumerate(tree.joints):
        if j.kind not in (SPHERICAL, FREE):
            a, b = tree.idx_q[i], tree.idx_v[i]
            out[a:a + j.nv] += change[b:b + j.nv]
    return out


def free_problem(mech, inp):
    """The compiled equilibrium problem (:class:`equilibrium.Problem`:
    residual, analytic tangent, Newton) of a mechanism without multipliers
    under checked inputs ``inp`` (:class:`Inputs`)."""
    tree = mech.tree
    act = _cached(mech, "_act_arrays", lambda: actuator_arrays(tree))
    K, _ = _cached(mech, "_dense_KD", lambda: dense_stiffness_damping(tree))
    coef = tendon_coefficients(act, inp.u)
    return eq.Problem(tree, act, K, inp.loads, inp.gravity, coef, inp.effort)


def _free_equilibrium(mech, inp, q, tol, max_iterations, max_load_steps, check_stability, tangent_hint):
    """:func:`solve_equilibrium` without multipliers: :func:`equilibrium.solve`
    (in the coordinates z of variable-strain segments, :class:`equilibrium.ReducedProblem`:
    then ``tangent`` is ``B^T K_t B``, a hint for the next solve of the same robot)."""
    with one_blas_thread():
        pb = free_problem(mech, inp)
        if mech.basis is not None:        # variable-strain segments: Newton in their coordinates z
            pb = eq.ReducedProblem(pb, mech.basis)
            q = pb.z_of(q)
        sol = eq.solve(pb, q, tol=tol, max_iterations=max_iterations, max_load_steps=max_load_steps,
                       check_stability=check_stability, tangent_hint=tangent_hint)
    lam = np.zeros(0)
    q1 = sol.q if mech.basis is None else pb.q_of(sol.q)
    return Equilibrium(q1.copy(), lam, _efforts_out(mech, lam, inp), {}, sol.iterations,
                       float(np.abs(sol.R).max(initial=0) / eq.force_scale(pb, sol.q, sol.R)), 0.0, sol.load_steps,
                       inp, sol.stable, sol.min_stiffness_eigenvalue, sol.tangent,
                       sol.tangent if check_stability and sol.stable else None)


def _scaled_inputs(mech, inp, t, q_start):
    pos = mech.joints_with("position")
    q_from = np.array([q_start[mech.tree.idx_q[i]] for i in pos])
    ld = inp.loads
    return Inputs(t * inp.u, t * inp.effort, q_from + t * (inp.q_cmd - q_from), inp.v_cmd,
                  LoadArrays(ld.joint, ld.x, t * ld.wrench, ld.world), t * inp.gravity)


def _continuation(mech, inp, path, q, lam, tol, max_iterations, max_load_steps, total, obstacles=(), stick=None):
    """The inputs raised in fractions t from ``q`` (adaptive steps), the
    constraints' targets ``path(t)`` (:func:`_base_path`)."""
    t, dt, steps = 0.0, 0.25, 0
    q_c, l_c = q.copy(), lam.copy()
    while t < 1.0:
        target = min(1.0, t + dt)
        targets = path(target)
        pb = _Equilibrium(mech, _scaled_inputs(mech, inp, target, q), targets, obstacles, stick)
        q_t, l_t, it, ok, R, phi, sc = _kkt_newton(pb, carry_base(mech, q_c, targets), l_c, tol, max_iterations)
        total += it
        steps += 1
        if ok:
            t, q_c, l_c = target, q_t, l_t
            dt = min(2 * dt, 1.0)
        else:
            dt *= 0.5
            if dt < 1.0 / max_load_steps / 64 or steps > 4 * max_load_steps:
                carried = " (a prescribed base brought that fraction of the way to its pose)" \
                    if getattr(path, "carries", False) else ""
                raise StaticsError(f"statics did not converge: reached load fraction {t:.4f}{carried}; the loads, "
                                   f"commands or constraints may be incompatible")
    return q_c, l_c, total, steps, R, phi, sc


# ----------------------------------------------------------------------------
# Dynamics
# ----------------------------------------------------------------------------

class _FreeState:
    """The plain state ThetaIntegrator advances (q, qdot, t)."""
    __slots__ = ("q", "qdot", "t")

    def __init__(self, q, qdot, t):
        self.q, self.qdot, self.t = q, qdot, t


_NO_POINTS = ContactPoints(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), (),
                           np.zeros(0))
_NO_PAIRS = np.zeros((0, 0), np.bool_)


def _new_contact_outputs(size):
    """The compiled contact step's output arrays for ``size`` (point,
    obstacle) pairs (:func:`engine.contact_step.contact_step`: index,
    obstacle, normal, gap, force, its derivatives, moment, slip, arms,
    spin, dM/dw)."""
    return (np.empty(size, np.int64), np.empty(size, np.int64), np.empty((size, 3)), np.empty(size),
            np.empty((size, 3)), np.empty((size, 3, 3)), np.empty((size, 3, 3)), np.empty((size, 3, 3)),
            np.empty((size, 3, 3)), np.empty((size, 3)), np.empty((size, 3)), np.empty((size, 3)),
            np.empty((size, 3)), np.empty(size), np.empty(size))


_NO_OUTPUTS = _new_contact_outputs(0)        # (shared: nothing is written into empty arrays)


def _contact_outputs(size):
    return _NO_OUTPUTS if size == 0 else _new_contact_outputs(size)


class MechanismSimulator:
    """Time integration of a mechanism with joint control and constraints:
    the theta-method step of :mod:`integrators` (theta = 1/2: implicit
    midpoint, 1: implicit Euler) with the constraint reactions and the
    position-controlled joints' efforts as multipliers; every constraint
    holds at the end of each step to ``constraint_tol`` (position level: no
    drift). State: ``t`` [s], ``q``, ``v``, ``a`` (the step's mean
    acceleration), ``lam``. Without multipliers a failing step is retried
    in up to 2**``max_substep_levels`` sub-steps, then (``full_newton``) by
    the dense Newton fallback (:class:`integrators.ThetaIntegrator`;
    ``reuse_factorisation``: its Newton matrix serves later steps while it
    contracts the error as a fresh one does; with constraint rows, the
    compiled KKT step's factors serve later steps while steps converge in 5
    iterations or fewer: results to the tolerance, not beyond as a fresh
    Newton matrix's quadratic convergence gives them). ``compiled``: the compiled
    steps (:mod:`engine.contact_step`, :mod:`engine.closed_step`) where they
    apply; False: the Python KKT step (a reference). Variable-strain
    segments (``mech.basis``) step in their coordinates: the reduced step
    (:class:`reduced_step.ReducedThetaIntegrator`, position-controlled joints
    eliminated) without constraint rows or contacts, else the compiled
    steps with the basis's Galerkin inverse (the Python KKT step projected
    on the basis their fallback). ``iterations``: the last
    call's Newton iterations a step; ``newton_iterations``: all of them so
    far; ``factorisations``: the Newton matrices factorised so far.

    >>> sim = MechanismSimulator(mech, dt=2e-3)
    >>> sim.step(positions={"pan": 0.2}, n=100)
    """

    def __init__(self, mech, dt, theta=0.5, q=None, v=None, *, tol=1e-10, constraint_tol=1e-12,
                 max_iterations=40, max_substep_levels=4, full_newton=True, reuse_factorisation=True,
                 obstacles=None, compiled=True, carried_secant=False):
        if not dt > 0 or not np.isfinite(dt):
            raise ValueError(f"dt: expected a positive time step [s], got {dt}")
        if not 0.5 <= theta <= 1.0:
            raise ValueError(f"theta: expected a value in [0.5, 1], got {theta}")
        tree = mech.tree
        self.mech, self.tree, self.dt, self.theta = mech, tree, float(dt), float(theta)
        self.tol, self.constraint_tol, self.max_iterations = tol, constraint_tol, max_iterations
        self.max_substep_levels = int(max_substep_levels)
        self.reuse_factorisation = bool(reuse_factorisation)
        self.carried_secant = bool(carried_secant)      # a prescribed base's end velocity (_carried_velocity)
        self.ws = Workspace(tree)
        self.act = _cached(mech, "_act_arrays", lambda: actuator_arrays(tree))
        self.K, self.D = _cached(mech, "_dense_KD", lambda: dense_stiffness_damping(tree))
        self.t = 0.0
        self.q = tree.q0.copy() if q is None else tree.check_q(np.array(q, float)).copy()
        self.v = np.zeros(tree.nv) if v is None else tree.check_v(np.array(v, float)).copy()
        self.a = np.zeros(tree.nv)
        if mech.basis is not None:
            on_basis(mech, basis_offset(mech, self.q), "q")
            on_basis(mech, self.v, "v")
        self.lam = np.zeros(mech.n_constraint_rows + len(mech.joints_with("position")))
        self.iterations = self.newton_iterations = self._kkt_factorisations = 0
        self.inputs = make_inputs(mech)
        self._held_of = None              # the Inputs _held was made of
        self.Ls = _length_scale(mech)
        self.contact = MemberContact(mech, obstacles)      # the robot file's obstacles by default
        self._obstacles0 = None           # moving obstacles: where they were at the step's start
        self._compiled_held = None        # the compiled contact step's inverse Newton matrix and inputs
        self.contacts = None              # the ContactState of the last step (at its theta point)
        # position-controlled joints without constraint rows: eliminated (their velocity prescribed, their
        # effort the residual's row) in the compiled contact step; 1-dof joints, whose update is q + h v
        pos = mech.joints_with("position")
        self._pos_v = np.array([tree.idx_v[i] for i in pos], dtype=np.int64)
        self._pos_q = np.array([tree.idx_q[i] for i in pos], dtype=np.int64)
        carried = _carried_base(mech)
        self._carried = None if carried is None else carried[1:3]   # a prescribed base's free joint (q, v offsets)
        self._fixed = np.zeros(tree.nv, dtype=np.bool_)
        self._fixed[self._pos_v] = True
        # the compiled step (engine.contact_step) serves every robot with obstacles, with constraint rows
        # (closed chains, a prescribed base) or without, and those without obstacles and constraint rows
        # whose position-controlled joints need more than the rod's integrator. A loop's constraint rows
        # couple joints across the loop and cannot be eliminated one joint at a time as a position command
        # can: they keep their multipliers (the Schur complement on them, as in engine.closed_step).
        one_dof = all(tree.joints[i].kind in (REVOLUTE, PRISMATIC) for i in pos)
        # (with variable-strain segments the unknowns are the basis's coordinates: the reduced step below
        # without multipliers; with them, the compiled steps' Newton on the velocities with the Galerkin
        # inverse B (B^T A B)^-1 B^T and the residual B^T R: step_matrix.invert_step_matrix, residual_sizes)
        eliminable = one_dof
        self._use_compiled_step = compiled and eliminable and (mech.n_constraint_rows == 0 or bool(self.contact))
        # constraint rows, no contacts: the compiled KKT step (engine.closed_step), the Python one its
        # fallback when it fails. Not a different physics: the contact step solves the same equations (the
        # same states to the bit on the four-bar, the parallel robot, the fixed-fixed beam) but its contact
        # set-up costs 14-19 us more a step (the four-bar: 16 -> 31 us)
        self._use_closed_step = compiled and mech.n_constraint_rows > 0 and eliminable and not self.contact
        self._closed_held = None          # its factors, constraint arrays and independent rows
        # no multipliers (a rod, a tree of soft members and effort-controlled or passive joints): the
        # engine's compiled O(n) integrator, the rod's (integrators.ThetaIntegrator)
        self._theta_integrator = None
        free = self.lam.size == 0 and not self.contact
        joints_only = compiled and mech.n_constraint_rows == 0 and not self.contact and one_dof
        if mech.basis is not None and (free or joints_only):
            # variable-strain segments: the step in their coordinates, position-controlled joints eliminated
            self._theta_integrator = ReducedThetaIntegrator(tree, self.ws, self.act, lambda t: self._held, self.dt,
                                                            mech.basis, self.K, self.D, self.theta, tol=tol,
                                                            max_iterations=max_iterations,
                                                            max_substep_levels=max_substep_levels,
                                                            prescribed=(self._pos_v, self._pos_q))
        elif free:
            self._theta_integrator = ThetaIntegrator(tree, self.ws, self.act, lambda t: self._held, self.dt, self.theta,
                                                     tol=tol, max_iterations=max_iterations,
                                                     max_substep_levels=max_substep_levels, full_newton=full_newton,
                                                     reuse_factorisation=reuse_factorisation)

    @property
    def factorisations(self):
        """Newton matrices factorised so far (every step's, with multipliers)."""
        ti = self._theta_integrator
        return ti.factorisations if ti is not None else self._kkt_factorisations

    def step(self, actuation=None, efforts=None, positions=None, loads=None, point_loads=(), targets=None,
             n=1, inputs=None, obstacles=None):
        """Advance n steps with these inputs held (positions: the commands the
        position-controlled joints reach at the end of each step; targets:
        world poses of constraints to the world, default their own;
        ``obstacles``: where the obstacles are at the end of the step, for
        obstacles that move: a simulator made with obstacles, the same
        number and kinds). Raises StepError (state unchanged) if a step fails."""
        if obstacles is not None and not self.contact:
            raise ValueError("obstacles: this simulator was made without obstacles (or its members have no "
                             "contact points); give them to MechanismSimulator(..., obstacles=...)")
        if inputs is not None:
            inp = inputs
        elif actuation is None and efforts is None and positions is None and loads is None and not point_loads:
            inp = self.__dict__.get("_no_inputs")       # the defaults, checked once (10 us a call of make_inputs)
            if inp is None:
                inp = self._no_inputs = make_inputs(self.mech)
        else:
            inp = make_inputs(self.mech, actuation, efforts, positions, None, loads, point_loads)
        self.inputs = inp
        if self._theta_integrator is not None:
            self._run_free(inp, int(n))          # the O(n) passes: no BLAS
            return self
        # the Python KKT step's scipy factorisations on one BLAS thread; the compiled steps' small
        # inverses gain nothing from the limit, which costs ~20 us a call to set (a step of the
        # four-bar takes 50 us)
        compiled = self._use_compiled_step or self._use_closed_step
        with contextlib.nullcontext() if compiled else one_blas_thread():
            for _ in range(int(n)):
                if self.contact:
                    self._move_obstacles(obstacles)
                    self._contact_step(inp, targets, self.dt, 0)
                elif self._use_compiled_step:     # position-controlled joints, eliminated; no contacts
                    self._contact_step(inp, targets, self.dt, 0)
                elif self._use_closed_step:
                    self._closed_or_kkt_step(inp, targets)
                else:
                    self._step(inp, targets)
        return self

    def _move_obstacles(self, obstacles):
        """The obstacles at the end of the next step (None: where they are)."""
        self._obstacles0 = None
        if obstacles is None:
            return
        obstacles = tuple(obstacles)
        if len(obstacles) != len(self.contact.obstacles) or any(
                a.kind != b.kind for a, b in zip(obstacles, self.contact.obstacles)):
            raise ValueError("obstacles: a moving obstacle keeps its kind, and the set its size "
                             f"({len(self.contact.obstacles)} obstacles)")
        self._obstacles0 = self.contact.obstacles
        self.contact = self.contact.with_obstacles(obstacles)

    def _contact_step(self, inp, targets, h, level):
        """One step of h with contacts: if Newton fails (a contact made or
        lost within the step), two halves, down to ``max_substep_levels``.
        With constraint rows the compiled step's failure is first retried by
        the Python step (as :meth:`_closed_or_kkt_step` does: its rows are
        taken again at the next step)."""
        try:
            if self._use_compiled_step:     # the compiled step
                try:
                    return self._compiled_step(inp, targets, h)
                except StepError:
                    if not self.mech.n_constraint_rows:
                        raise
                    self._compiled_held = None
            return self._step(inp, targets, h)
        except StepError:
            if level >= self.max_substep_levels:
                raise
        state = (self.q.copy(), self.v.copy(), self.lam.copy(), self.t, self.a.copy())
        start, end = self._obstacles0, self.contact
        mid = end if start is None else end.with_obstacles(
            moved(o0, 0.5 * (o1.a - o0.a)) for o0, o1 in zip(start, end.obstacles))   # moving obstacles: halfway
        try:
            self.contact = mid
            self._contact_step(inp, targets, 0.5 * h, level + 1)
            self._obstacles0 = None if start is None else mid.obstacles
            self.contact = end
            self._contact_step(inp, targets, 0.5 * h, level + 1)
        except StepError:
            self.q, self.v, self.lam, self.t, self.a = state
            self._obstacles0, self.contact = start, end
            raise

    def _compiled_step(self, inp, targets, h):
        """One step of h with contacts, or with position-controlled joints
        and no constraint rows: :func:`engine.contact_step.contact_step`
        (the Newton iteration of :meth:`_step`, compiled; constraint rows by
        their Schur complement, as :meth:`_closed_step`), its inverse Newton
        matrix kept for the next step while the same points touch. A position-controlled joint
        is eliminated: its end-of-step velocity makes ``q_1 = q_cmd``
        (``q_1 = q_0 + h v_theta``), and its multiplier (the effort that
        holds it) is its residual row, as the KKT step's ``q_j = q_cmd``
        row gives."""
        tree, ws, contact = self.tree, self.ws, self.contact
        if contact:
            pts, obstacles, allowed = contact.points, contact.all, contact.allowed
        else:                            # nothing to touch: the step of the position-controlled joints
            pts, obstacles, allowed = _NO_POINTS, (), _NO_PAIRS
        obs = obstacle_arrays(obstacles)
        start = self._obstacles0
        obs0 = obs if start is None else obstacle_arrays(tuple(start) + tuple(self.mech.shapes))
        held = self._compiled_held
        if held is None or held["h"] != h or held["obstacles"] != len(obstacles):
            held = self._compiled_held = self._held_step_arrays(h, targets, inp)
            held.update(obstacles=len(obstacles), key=np.zeros(len(pts) * len(obstacles) + 1, np.int64),
                        still=obs.body >= 0)
        moving = held["still"] if start is None else (obs.body >= 0) | np.array(
            [a is not b for a, b in zip(start, contact.obstacles)] + [False] * len(self.mech.shapes))
        arr, nc = self._step_arrays_of(held, targets, inp), held["nc"]
        out = _contact_outputs(len(pts) * len(obstacles))
        v1, q1, pt, R = self.v.copy(), np.empty(tree.nq), np.empty((len(pts), 3)), arr.R
        lam = self.lam[:nc].copy()
        pv, th, length = self._pos_v, self.theta, max(self.Ls, 1.0)
        if pv.size:
            v1[pv] = ((inp.q_cmd - self.q[self._pos_q]) / h - (1 - th) * self.v[pv]) / th
        it, status, c, fresh, lam_next = contact_step(
            ws.m, ws.w, self.act, held["loads"], inp.gravity, held["coef"], inp.effort, arr, tree.nq == tree.nv,
            self.q, self.v, h, th, self.tol, 1e-14 * length / h, self.max_iterations, self.constraint_tol * length,
            self._lam_force(held) * length, lam, pts.joint, pts.x, pts.offset, pts.radius, pts.modulus,
            pts.weight, allowed, obs, obs0, *self._posed_arrays(obs0, obs), moving, held["key"], held["reuse"], v1,
            q1, pt, *out)
        self._kkt_factorisations += fresh
        # kept for the next step if it converged fast: without contacts the matrix changes smoothly
        # (the pan-tilt arm: 0.46 factorisations a step, 181 -> 154 us); contacts' stiffness jumps
        held["reuse"] = status == 0 and it <= (2 if contact else 5)
        if status:
            why = {1: f"Newton did not converge in {self.max_iterations} iterations", 3: "non-finite residual",
                   4: "singular Newton matrix"}[status]
            if nc and status == 1:
                why += f" (constraint error {np.abs(arr.phi).max(initial=0):.3g})"
            raise StepError(f"step at t = {self.t:.6g} s: {why}")
        idx = out[0][:c]
        self.a = (v1 - self.v) / h
        if pv.size:      # their velocity as the KKT step leaves it (MechanismSimulator._step), their efforts
            v1[pv] = inp.v_cmd if inp.v_cmd is not None else (q1[self._pos_q] - self.q[self._pos_q]) / h
        if nc or pv.size:
            self.lam = np.concatenate([lam, R[pv]]) if pv.size else lam
            held["lam_max"] = (lam_next, self.lam)
        self._carried_velocity(self.q, q1, v1, h)
        self.q, self.v = q1, v1
        self.contacts = None
        if contact:
            n_, gap, F, dF, dV, dFf, dVf, M, slip, arm, barm, spin, dW = (x[:c] for x in out[2:])
            self.contacts = ContactState(idx, out[1][:c], pt[idx], n_, gap, F, dF, dV, M, slip,
                                         body=obs.body[out[1][:c]], arm=arm, body_arm=barm, spin=spin, dM_dw=dW,
                                         dFf_dp=dFf, dFf_dv=dVf, radius=pts.radius[idx])
        self.t += h
        self.iterations = it
        self.newton_iterations += it

    def _carried_velocity(self, q0, q1, v1, h):
        """``carried_secant``: a prescribed base leaves the step with the
        twist of its motion over it, ``log(g0^-1 g1) / h`` (body axes), as a
        position-controlled joint leaves it with (q1 - q0) / h: not the
        midpoint rule's v1 = 2 s - v0, which feeds v0 back and grows without
        bound in alternating signs when the poses come in jerks (moved one
        step, held the next: a carrier's stream slower than the steps). First
        order on a smooth motion (the velocity half a step late), so it is
        for streamed poses (the twin's), not trajectories (the default)."""
        if self._carried is None or not self.carried_secant:
            return
        iq, iv = self._carried
        g0, g1 = _free_pose(q0[iq:iq + 7]), _free_pose(q1[iq:iq + 7])
        v1[iv:iv + 6] = log_se3(se3_inv(g0) @ g1) / h

    def _closed_or_kkt_step(self, inp, targets):
        """One step with constraint rows: the compiled KKT step
        (:func:`engine.closed_step.closed_step`), or, if it fails (its
        redundant rows changed, Newton stalled), the Python one."""
        try:
            return self._closed_step(inp, targets, self.dt)
        except StepError:
            self._closed_held = None
        self._step(inp, targets)

    def _held_step_arrays(self, h, targets, inp):
        """What a compiled step (closed_step, contact_step) keeps for the
        next ones at step h: its :class:`ClosedArrays` (the constraints, the
        independent rows at the current state, the factors), the multipliers'
        size the last step left (``lam_max``), whether the targets moved."""
        tree, mech = self.tree, self.mech
        nc = mech.n_constraint_rows
        B, P = self._basis_arrays()
        rows = np.zeros(0, np.int64)
        if nc:
            _, G = constraint_rows(mech, self.ws, self.q, targets, inp.q_cmd)
            # (on a basis, the rows independent in its coordinates: a loop it cannot bend shows as redundant)
            rows = independent_rows(G[:nc] @ B if B.shape[1] else G[:nc]).astype(np.int64)
        nv, mr = tree.nv, len(rows)
        cj, cx, ckind, crows, csize, ctarget = self._closed_arrays(None)
        z = np.zeros
        return dict(h=h, nc=nc, rows=rows, reuse=False, lam_max=None, moved=False,
                    arrays=ClosedArrays.of(self.K, self.D, tree.q0, cj, cx, ckind, crows, csize, ctarget.copy(), rows,
                                           self._fixed, z((nv, nv)), z((nv, nv)), z((nv, mr)), z((mr, mr)),
                                           z((mr, nv)), z((mr, nv)), np.empty(nv), np.empty(nc), B, P))

    def _basis_arrays(self):
        """(B, (B^T B)^-1 B^T) of the robot's variable-strain segments for
        the compiled steps, or (nv, 0) and (0, nv) arrays: no basis."""
        B = self.mech.basis
        if B is None:
            return np.zeros((self.tree.nv, 0)), np.zeros((0, self.tree.nv))
        return B, np.linalg.solve(B.T @ B, B.T)

    def _step_arrays_of(self, held, targets, inp):
        """The held ClosedArrays with this step's constraint targets, and
        the inputs' arrays (once per Inputs) in ``held``."""
        c = held["arrays"]
        moved = targets is not None and any(t is not None for t in targets)
        if moved or held["moved"]:              # the constraints' world targets of this step (or back to their own)
            c.ctarget[:] = self._closed_arrays(targets)[5]
            held["moved"] = moved
        if held.get("inputs") is not inp:
            held.update(inputs=inp, coef=tendon_coefficients(self.act, inp.u), loads=concat_loads(inp.loads))
        return c

    def _lam_force(self, held):
        """The multipliers' and held efforts' size as the last compiled step
        left it (else from ``self.lam``: set from outside)."""
        lam_max = held["lam_max"]
        if lam_max is None or lam_max[1] is not self.lam:
            return np.abs(self.lam).max(initial=0)
        return lam_max[0]

    def _closed_arrays(self, targets):
        """The constraints' arrays for :func:`engine.closed_step.closed_step`:
        frames (joint, x), kinds, rows C (k, 6, 6) and sizes, world targets."""
        mech = self.mech
        cs = mech.constraints
        arrays = mech.__dict__.get("_closed_arrays")
        if arrays is None:
            joint, x = _constraint_points(mech)
            crows = np.zeros((len(cs), 6, 6))
            for k, c in enumerate(cs):
                crows[k, :c.size] = c.rows()
            arrays = (joint, kernel_array(x), np.array([CLAMPED if c.kind == "clamped" else 0 for c in cs], np.int64),
                      crows, np.array([c.size for c in cs], np.int64),
                      np.ascontiguousarray([np.eye(4) if c.target is None else c.target for c in cs],
                                           dtype=float).reshape(-1, 4, 4))
            object.__setattr__(mech, "_closed_arrays", arrays)
        if targets is None or all(t is None for t in targets):
            return arrays
        ctarget = arrays[5].copy()
        for k, t in enumerate(targets):
            if t is not None:
                ctarget[k] = t
        return arrays[:5] + (ctarget,)

    def _closed_step(self, inp, targets, h):
        """One step of h with constraint rows and no contacts: the Newton
        iteration of :meth:`_step`, compiled (the KKT system by its Schur
        complement on the constraint rows); its factors kept for the next
        step while steps converge fast, as :meth:`_compiled_step` does. The
        position-controlled joints eliminated as there. Raises StepError
        (state unchanged) if it fails."""
        tree, ws = self.tree, self.ws
        held = self._closed_held
        if held is None or held["h"] != h:
            held = self._closed_held = self._held_step_arrays(h, targets, inp)
        c, nc = self._step_arrays_of(held, targets, inp), held["nc"]
        R, phi = c.R, c.phi                      # (scratch of the kernel's: R[pv] copied out below)
        v1, q1 = self.v.copy(), np.empty(tree.nq)
        lam = self.lam[:nc].copy()
        pv, th, length = self._pos_v, self.theta, max(self.Ls, 1.0)
        if pv.size:
            v1[pv] = ((inp.q_cmd - self.q[self._pos_q]) / h - (1 - th) * self.v[pv]) / th
        it, status, fresh, lam_next = closed_step(
            ws.m, ws.w, self.act, held["loads"], inp.gravity, held["coef"], inp.effort, c, tree.nq == tree.nv,
            self.q, self.v, h, th, self.tol, 1e-14 * length / h, self.max_iterations, self.constraint_tol * length,
            self._lam_force(held) * length, held["reuse"], v1, lam, q1)
        self._kkt_factorisations += fresh
        held["reuse"] = self.reuse_factorisation and status == 0 and it <= 5
        if status:
            why = {1: f"Newton did not converge in {self.max_iterations} iterations (constraint error "
                      f"{np.abs(phi).max(initial=0):.3g})", 3: "non-finite residual", 4: "singular Newton matrix"}[status]
            raise StepError(f"step at t = {self.t:.6g} s: {why}")
        self.a = (v1 - self.v) / h
        if pv.size:      # their velocity as the KKT step leaves it, their efforts
            v1[pv] = inp.v_cmd if inp.v_cmd is not None else (q1[self._pos_q] - self.q[self._pos_q]) / h
        self.lam = np.concatenate([lam, R[pv]]) if pv.size else lam
        held["lam_max"] = (lam_next, self.lam)
        self._carried_velocity(self.q, q1, v1, h)
        self.q, self.v = q1, v1
        self.contacts = None
        self.t += h
        self.iterations = it
        self.newton_iterations += it

    def _posed_arrays(self, obs0, obs):
        """(P0, P1, Pt): the obstacles' arrays the compiled step poses the
        bodies' shapes into at the step's start, end and theta point (the
        given ones when no body carries a shape: nothing to pose)."""
        if not self.mech.shapes:
            return obs0, obs, obs
        return posable(obs0), posable(obs), posable(obs)

    def _run_free(self, inp, n):
        """n steps of :class:`integrators.ThetaIntegrator` (no multipliers)."""
        if self._held_of is not inp:         # the same inputs held again (a twin steps them at its rate)
            coef = tendon_coefficients(self.act, inp.u)
            self._held, self._held_of = (inp.loads, inp.gravity, coef, inp.effort), inp
        integ = self._theta_integrator
        integ.last_a = self.a
        if self._pos_v.size:                 # (the reduced step: position-controlled joints eliminated)
            integ.command = (inp.q_cmd, inp.v_cmd)
        state = _FreeState(self.q, self.v, self.t)
        it0 = integ.iterations
        info = integ.run(state, n)          # the converged steps in one compiled call
        self.q, self.v, self.t, self.a = state.q, state.qdot, state.t, integ.last_a
        if self._pos_v.size:
            self.lam = integ.efforts.copy()
        self.iterations = (integ.iterations - it0) // max(n, 1)
        self.newton_iterations += integ.iterations - it0
        if not info.converged:
            raise StepError(f"step at t = {state.t:.6g} s: Newton did not converge in {integ.max_iterations} "
                            f"iterations, in sub-steps either")

    def _newton_matrix(self, inp, coef, ld, qt, q1, targets, contacts=None, h=None):
        """Factors of the step's Newton matrix at (q_t, lambda):
        ``[[(M + th h D + (th h)^2 Kt)/h, -G_t^T], [th h G_1, 0]]`` with Kt
        the static tangent of the elastic forces, loads and tendons."""
        tree, m, w = self.tree, self.ws.m, self.ws.w
        h, th = self.dt if h is None else h, self.theta
        z = self.ws.zeros_v
        passes.forward_pass(m, w, qt, z, z, 0)
        Mq = np.zeros((tree.nv, tree.nv))
        passes.crba_pass(m, w, Mq)
        passes.rnea_pass(m, w, ld, inp.gravity, np.empty(tree.nv), True)
        Kt = self.K.copy()
        static_tangent_pass(m, w, ld, inp.gravity, Kt)
        actuation_tangent_pass(m, w, self.act, coef, Kt)
        Dt = self.D
        if contacts is not None:
            Dt = self.D.copy()
            self.contact.add_stiffness(self.ws, contacts, Kt, Dt=Dt)
        _, Gt = constraint_rows(self.mech, self.ws, qt, targets, inp.q_cmd)
        _, G1 = constraint_rows(self.mech, self.ws, q1, targets, inp.q_cmd)
        A = (Mq + th * h * Dt + (th * h) ** 2 * Kt) / h
        self._kkt_factorisations += 1
        T = self.mech.basis
        if T is not None:        # variable-strain segments: the Newton unknowns are their coordinates' rates
            A, Gt, G1 = T.T @ A @ T, Gt @ T, G1 @ T
        return factor_kkt(A, Gt, th * h * G1)

    def _step(self, inp, targets, h=None):
        """One theta step by modified Newton: the Newton matrix is factorised
        at the first iteration and again only when the iteration slows down
        (update shrinking less than fourfold)."""
        tree, m, w = self.tree, self.ws.m, self.ws.w
        h, th = self.dt if h is None else h, self.theta
        q0, v0 = self.q, self.v
        v1 = v0.copy()
        if self._pos_v.size:     # the prescribed joints reach their commands from the first iterate (a friction's
            v1[self._pos_v] = ((inp.q_cmd - q0[self._pos_q]) / h - (1 - th) * v0[self._pos_v]) / th   # cut updates
        lam = self.lam.copy()                                         # would otherwise cut their rows' too)
        coef = tendon_coefficients(self.act, inp.u)
        npos = len(self.mech.joints_with("position"))
        pos_v = np.array([tree.idx_v[i] for i in self.mech.joints_with("position")], dtype=np.int64)
        qt = np.empty(tree.nq)
        q1 = np.empty(tree.nq)
        R_full = np.empty(tree.nv)
        T = self.mech.basis
        fac, refactor, prev, first, Rs = None, True, np.inf, 0.0, 1e-300
        last, backtracks = None, 0          # the last Newton update (dv, dlambda, |R| before it), halvings of it
        for it in range(1, self.max_iterations + 1):
            vt = (1 - th) * v0 + th * v1
            acc = (v1 - v0) / h
            integrate_pass(m, q0, vt, th * h, qt)
            integrate_pass(m, q0, vt, h, q1)
            ld = concat_loads(inp.loads, constraint_loads(self.mech, lam))
            contacts = None
            if self.contact:              # the step's mean contact forces (energy-consistent)
                if it == 1:
                    start = self.contact.motion(self.ws, q0, v0, self._obstacles0)
                contacts = self.contact.step_state(self.ws, start, q1, qt, h, th, self._obstacles0)
            if contacts is not None:
                ld = concat_loads(ld, self.contact.loads(contacts))
            effort = inp.effort.copy()
            if npos:
                effort[pos_v] += lam[len(lam) - npos:]
            if refactor:
                try:
                    fac = self._newton_matrix(inp, coef, ld, qt, q1, targets, contacts, h)
                except np.linalg.LinAlgError:
                    raise StepError(f"step at t = {self.t:.6g} s: singular Newton matrix") from None
                refactor = False
            residual_pass(m, w, self.act, ld, inp.gravity, coef, effort, qt, vt, acc, R_full, False)
            R = R_full if T is None else T.T @ R_full      # variable-strain segments: on their basis
            phi1, _ = constraint_rows(self.mech, self.ws, q1, targets, inp.q_cmd)
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(phi1))):
                raise StepError(f"step at t = {self.t:.6g} s: non-finite residual")
            nR = np.abs(R).max(initial=0)
            phi_ok = np.abs(phi1).max(initial=0) <= self.constraint_tol * max(self.Ls, 1.0)
            if it == 1:
                Rs = max(nR, np.abs(lam).max(initial=0) * max(self.Ls, 1.0), 1e-300)
                # round-off of the forces: the elastic ones (a robot resting on obstacles steps from an
                # equilibrium whose residual is this noise; amplified by light sections it never settles)
                noise = 1e-9 * np.abs(self.K @ (qt - tree.q0)).max(initial=0) if tree.nq == tree.nv else 0.0
            if phi_ok and forces_balanced(nR, Rs, self.tol, noise):
                break              # balanced: forces to tol of their scale, constraints held
            if last is not None and nR > last[2] and backtracks < 4 and contacts is not None and len(contacts):
                # the residual grew: back along the last update (a contact's friction flips between
                # fast slips of opposite signs under full Newton steps; without contacts a constraint's
                # correction may rightly raise the residual a first time)
                dv, dl = 0.5 * last[0], 0.5 * last[1]
                v1 -= dv
                lam -= dl
                last, backtracks = (dv, dl, last[2]), backtracks + 1
                continue
            dv, dl = solve_factored(fac, R, phi1)
            if T is not None:
                dv = T @ dv
            if contacts is not None and len(contacts):
                # no friction jumps across its stiction zone (the workspace is posed at q_t)
                frac = self.contact.update_fraction(self.ws, contacts, dv)
                dv, dl = frac * dv, frac * dl
            last, backtracks = (dv, dl, nR), 0
            v1 += dv
            lam += dl
            ndv = np.abs(dv).max(initial=0)
            if it == 1:
                first = ndv
            vs = max(np.abs(v1).max(initial=0), np.abs(v0).max(initial=0), first, 1e-300)
            # below this an update is round-off for any motion of the robot (a length scale per step)
            floor = 1e-14 * max(self.Ls, 1.0) / h
            if phi_ok and update_converged(ndv, vs, self.tol, floor, prev, it > 2):
                break              # converged, or stalled at round-off
            refactor = it > 1 and ndv > 0.25 * prev
            prev = ndv
        else:
            raise StepError(f"step at t = {self.t:.6g} s: Newton did not converge in {self.max_iterations} "
                            f"iterations (constraint error {np.abs(phi1).max(initial=0):.3g})")
        vt = (1 - th) * v0 + th * v1
        integrate_pass(m, q0, vt, h, q1)
        self.a = (v1 - v0) / h              # the step's mean acceleration (its forces' state)
        if npos:
            # a position-controlled joint moves at its commanded velocity (given) or, without one, at
            # its position change over the step: not at the midpoint rule's v1 = 2 dq/h - v0, which
            # would alternate in sign for ever after a change of the commanded acceleration
            iq = np.array([tree.idx_q[i] for i in self.mech.joints_with("position")], dtype=np.int64)
            v1 = v1.copy()
            v1[pos_v] = inp.v_cmd if inp.v_cmd is not None else (q1[iq] - q0[iq]) / h
        self._carried_velocity(q0, q1, v1, h)
        self.q, self.v, self.lam = q1.copy(), v1, lam
        self.contacts = contacts
        self.t += h
        self.iterations = it
        self.newton_iterations += it

    def start_multipliers(self, inputs=None, targets=None):
        """Accelerations and multipliers of the current state when the
        constraint rows' accelerations vanish (``G a = -dG/dt v``, evaluated
        at rest: the t = 0 state of a run that starts at rest): the efforts
        and reactions a run reports before its first step."""
        inp = self.inputs if inputs is None else inputs
        tree, m, w = self.tree, self.ws.m, self.ws.w
        lam0 = np.zeros_like(self.lam)
        coef = tendon_coefficients(self.act, inp.u)
        bias = np.empty(tree.nv)
        residual_pass(m, w, self.act, concat_loads(inp.loads, constraint_loads(self.mech, lam0)), inp.gravity,
                      coef, inp.effort, np.ascontiguousarray(self.q), self.v, np.zeros(tree.nv), bias, False)
        M = np.zeros((tree.nv, tree.nv))
        passes.forward_pass(m, w, np.ascontiguousarray(self.q), self.ws.zeros_v, self.ws.zeros_v, 0)
        passes.crba_pass(m, w, M)
        phi, G = constraint_rows(self.mech, self.ws, self.q, targets, inp.q_cmd)
        T = self.mech.basis
        if T is None:
            a, lam = solve_kkt(M, G, G, bias, np.zeros(len(phi)))
        else:                    # variable-strain segments: the accelerations on their basis
            a, lam = solve_kkt(T.T @ M @ T, G @ T, G @ T, T.T @ bias, np.zeros(len(phi)))
            a = T @ a
        self.a, self.lam, self.inputs = a, lam, inp
        return self

    # --- outputs ---------------------------------------------------------------
    def joint_efforts(self):
        """{joint: effort} (N m or N) of the last step (inputs or multipliers)."""
        return _efforts_out(self.mech, self.lam, self.inputs)

    def constraint_wrenches(self):
        return constraint_wrenches(self.mech, self.lam)

    def constraint_error(self, targets=None):
        """max |Phi| [m, rad] of the constraints (not the motion rows) now."""
        phi, _ = constraint_rows(self.mech, self.ws, self.q, targets, self.inputs.q_cmd)
        nc = self.mech.n_constraint_rows
        return float(np.abs(phi[:nc]).max(initial=0))

    def energy(self):
        """(kinetic, potential) [J]: 1/2 v^T M v and the elastic plus gravity
        potential (rigid bodies and soft points), and the contacts' stored
        energy, at the current state."""
        tree = self.tree
        M = crba(tree, self.ws, self.q)
        T = 0.5 * self.v @ M @ self.v
        qd = _coordinate_offsets(tree, self.q)
        V = 0.5 * qd @ self.K @ qd
        g = self.inputs.gravity
        a = tree.arrays
        alg_ws = self.ws
        forward_kinematics(tree, alg_ws, self.q)
        for i, j in enumerate(tree.joints):
            if a.rigid_mass[i]:
                mass = j.inertia[0, 0]
                c = np.array([j.inertia[5, 1], j.inertia[3, 2], j.inertia[4, 0]]) / mass
                gout = alg_ws.work.g_out[i]
                V -= mass * g @ (gout[:3, :3] @ c + gout[:3, 3])
            if j.kind == 5:
                npt = a.npt[i]
                P = point_poses(tree, alg_ws, self.q, [i] * npt, a.px[i, :npt])
                V -= np.sum(a.pw[i, :npt] * a.mc[i, 0] * (P[:, :3, 3] @ g))
        if self.contact:
            V += self.contact.potential(self.ws, self.q)
        return float(T), float(V)

