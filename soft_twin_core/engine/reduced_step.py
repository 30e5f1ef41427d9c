"""The theta step of a robot whose velocities lie on a basis, compiled: the
Newton loop of :class:`ReducedThetaIntegrator` (below; variable-strain
segments, ``v = B w``), whose Python glue cost as much as the passes it
drove, and the integrator that calls it.

Galerkin: the step's residual R(v1) (:func:`integrators.residual_pass`, the
same O(n) passes over the sections as a PCS robot's) is projected on the
basis, ``r = B^T R(B w1) = 0``, and solved for the coordinates' rates w1
by modified Newton with

    A_z = B^T (M + theta h D + (theta h)^2 K) B

(:func:`basis_newton_matrix`: the mass matrix in z by
:func:`passes.projected_mass_pass`, an nz x nz Cholesky check and inverse), made at a step's first iterate when none is held for
this h and again when an update shrinks less than fourfold, and held for
the next steps while it serves (a step on it that took more iterations
beyond the last fresh one's than a new matrix costs, :func:`matrix_cost`,
has the next step make one). The predictor extrapolates the last two
steps' accelerations, as the O(n) step's. Position-controlled 1-dof joints (identity
columns of B, the ``fixed`` coordinates) are eliminated: their rates put
them at their commands at the end of the step, the Newton runs over the
other coordinates, and their rows of r are the efforts that hold them."""

import numba as nb
import numpy as np
from numba.experimental import structref

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.integrators import StepLoop, accept_step, integrate_pass, residual_pass
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import ArraysRef, ArraysType, declare
from soft_twin_core.engine.kernels.spatial import FALSE, _jit, _jit_inline, _jit_inner
from soft_twin_core.engine.step_matrix import free_newton_update

_NO_COMMAND = np.zeros(0)          # (reduced_steps: no position-controlled joints, or no velocity command)

# What a robot on a basis keeps from step to step, one structref (as closed_step.ClosedArrays)
BASIS_FIELDS = (
    "B", "BT", "P",           # the basis (nv, nz), its transpose, its least-squares projector (B^T B)^-1 B^T
    "Dz", "Kz",               # B^T D B, B^T K B (nz, nz)
    "fixed",                  # (nz,) bool: the coordinates of position-controlled joints
    "pv", "pq", "pz",         # their velocity, position and basis indices
    "Ainv",                   # (nz, nz): the held inverse Newton matrix (identity on the fixed coordinates)
    "r",                      # out (nz,): the projected residual of the last iterate
    "efforts",                # out (len(pz),): the efforts holding the fixed joints at the last converged step
)


@structref.register
class BasisArraysType(ArraysType):
    pass


class BasisArrays(ArraysRef):
    """The arrays of :data:`BASIS_FIELDS` as :func:`reduced_steps` takes them."""
    FIELDS = BASIS_FIELDS


declare(BasisArrays, BasisArraysType, BASIS_FIELDS)


@nb.njit(cache=True)
def _make_basis_ref(B, BT, P, Dz, Kz, fixed, pv, pq, pz, Ainv, r, efforts):
    return BasisArrays(B, BT, P, Dz, Kz, fixed, pv, pq, pz, Ainv, r, efforts)


BasisArrays.make = _make_basis_ref


@_jit_inline
def basis_newton_matrix(m, w, qt, th, b, zeros):
    """b.Ainv = (B^T (M(q_t) + th D + th^2 K) B)^-1, the fixed coordinates'
    rows and columns the identity's (the upper triangle made, the matrix
    symmetric). False when it is not positive definite (then no step with
    it) or not finite."""
    nz = b.B.shape[1]
    passes.forward_pass(m, w, qt, zeros, zeros, passes.POSES)
    A = np.empty((nz, nz))
    passes.projected_mass_pass(m, w, b.B, A)
    for i in range(nz):
        for j in range(i, nz):
            if b.fixed[i] or b.fixed[j]:
                a = 1.0 if i == j else 0.0
            else:
                a = A[i, j] + th * b.Dz[i, j] + th * th * b.Kz[i, j]
            A[i, j] = a
            A[j, i] = a
    return passes.spd_inverse(A, nz, b.Ainv)


@_jit_inner
def _predictor(b, q0, v0, a_last, a_prev, have_prev, h, theta, q_cmd, w1):
    """w1 = P (v0 + h a) (the rates on the basis nearest the velocity the
    accelerations extrapolate to: a = 2 a_last - a_prev from two real
    steps, ``have_prev``, else a_last, as the O(n) step's predictor), the
    fixed coordinates' the rates that put their joints at q_cmd at the end
    of the step."""
    nv, nz = b.B.shape
    for c in range(nz):
        s = 0.0
        for k in range(nv):
            a = 2.0 * a_last[k] - a_prev[k] if have_prev else a_last[k]
            s += b.P[c, k] * (v0[k] + h * a)
        w1[c] = s
    for j in range(b.pz.shape[0]):
        w1[b.pz[j]] = ((q_cmd[j] - q0[b.pq[j]]) / h - (1.0 - theta) * v0[b.pv[j]]) / theta


@_jit_inner
def _step_velocities(B, w1, v0, h, theta, v1, vt, acc):
    """v1 = B w1, the step's mean velocity vt = (1 - theta) v0 + theta v1
    and acceleration acc = (v1 - v0) / h; returns max(|v1|, |v0|)."""
    vmax = 0.0
    for k in range(v0.shape[0]):
        s = 0.0
        for c in range(w1.shape[0]):
            s += B[k, c] * w1[c]
        v1[k] = s
        vt[k] = (1.0 - theta) * v0[k] + theta * s
        acc[k] = (s - v0[k]) / h
        vmax = max(vmax, abs(s), abs(v0[k]))
    return vmax


@_jit_inner
def _project(BT, R, r):
    """r = B^T R (the virtual power of the forces R on the basis's
    motions); False if not finite."""
    finite = True
    for c in range(r.shape[0]):
        s = 0.0
        for k in range(R.shape[0]):
            s += BT[c, k] * R[k]
        r[c] = s
        if not np.isfinite(s):
            finite = False
    return finite


@_jit_inner
def _largest_on_basis(B, dw):
    """max |B dw|: the size of an update in velocities."""
    out = 0.0
    for k in range(B.shape[0]):
        s = 0.0
        for c in range(dw.shape[0]):
            s += B[k, c] * dw[c]
        out = max(out, abs(s))
    return out


@_jit
def reduced_steps(m, w, act, ld, g, coef, effort, q, v, a_last, a_prev, have_prev, steps_before, h, theta, tol,
                  max_it, n, b, q_cmd, v_cmd, fresh, refresh_cost, stats):
    """Up to n theta steps of h with constant inputs, each from the
    predictor of :func:`_predictor` (a_last zeros and not ``have_prev``:
    from v; ``steps_before``: the steps taken before this call, the
    extrapolation from two real steps only, never from the initial zero
    acceleration), as :meth:`ReducedThetaIntegrator._newton`. q, v,
    a_last, a_prev advance in place after every converged step; a step that does not
    converge is left to the caller as it was. ``fresh``: no Newton matrix
    of this h is held in b.Ainv. ``v_cmd`` (len(pz),) or empty: the fixed
    joints' velocity at the end of a step (empty: their change over the
    step). Returns the steps done; stats[0] += their Newton iterations,
    stats[1] += matrices made, stats[2] = 1 if b.Ainv holds one of this h,
    stats[3] = the failed step's status (1 not converged in max_it,
    3 non-finite, 4 no positive definite matrix); stats[4] (in and out):
    the iterations of the last step that made its matrix (0: none yet).
    A step on a held matrix that took more than ``refresh_cost`` (what a
    new matrix costs, in iterations) beyond that has the next step make a
    new one: it pays for itself if the next step's iterations fall back."""
    nv, nz = b.B.shape
    npz = b.pz.shape[0]
    w1 = np.empty(nz)
    v1 = np.empty(nv)
    vt = np.empty(nv)
    acc = np.empty(nv)
    qt = np.empty(q.shape[0])
    q1 = np.empty(q.shape[0])
    R = np.empty(nv)
    rh = np.empty(nz)
    dw = np.empty(nz)
    zeros = np.zeros(nv)
    th = theta * h
    held = not fresh
    stats[2] = 1.0 if held else 0.0
    for s in range(n):
        _predictor(b, q, v, a_last, a_prev, have_prev, h, theta, q_cmd, w1)
        qmax = 1.0
        for k in range(q.shape[0]):
            qmax = max(qmax, abs(q[k]))
        floor = 1e-14 * qmax / h             # the round-off of q
        prev = np.inf
        status = 1
        it = 0
        made = not held
        while it < max_it:
            it += 1
            vmax = _step_velocities(b.B, w1, v, h, theta, v1, vt, acc)
            integrate_pass(m, q, vt, th, qt)
            if not held:
                stats[1] += 1
                stats[2] = 0.0
                if not basis_newton_matrix(m, w, qt, th, b, zeros):
                    status = 4
                    break
                held = True
                stats[2] = 1.0
            residual_pass(m, w, act, ld, g, coef, effort, qt, vt, acc, R, FALSE)
            if not _project(b.BT, R, b.r):
                status = 3
                break
            for c in range(nz):
                rh[c] = h * b.r[c]
            free_newton_update(b.Ainv, rh, b.fixed, dw)
            for c in range(nz):
                w1[c] += dw[c]
            ndv = _largest_on_basis(b.B, dw)
            if ndv <= max(tol * vmax, floor):
                status = 0
                break
            if it > 1 and ndv > 0.25 * prev:
                held = False                 # slow: a fresh matrix at the next iterate
            prev = ndv
        if status != 0:
            stats[3] = status
            return s
        stats[0] += it
        if made:
            stats[4] = it
        elif stats[4] > 0.0 and it > stats[4] + refresh_cost:
            held = False
            stats[2] = 0.0           # (also for the next call)
        _step_velocities(b.B, w1, v, h, theta, v1, vt, acc)
        integrate_pass(m, q, vt, h, q1)
        for j in range(npz):
            b.efforts[j] = b.r[b.pz[j]]
            pv, pq = b.pv[j], b.pq[j]
            v1[pv] = v_cmd[j] if v_cmd.shape[0] > 0 else (q1[pq] - q[pq]) / h
        accept_step(q, v, a_last, a_prev, q1, v1, h)
        have_prev = steps_before + s > 0
    return n


def matrix_cost(model, nz):
    """What :func:`basis_newton_matrix` costs in Newton iterations of
    :func:`reduced_steps` on ``model`` with nz coordinates: both are O(n)
    in the joints, the matrix's recursion O(nz) a joint and its sum
    O(nz^2) a mass point, an iteration's projections O(nz) a coordinate.
    Fitted to the benchmark cantilever (Legendre orders 1, 3, 5) on 16 to
    128 sections with the midpoint step (two mass points a section) and 4
    to 16 with ``magnus: 4`` (one every other section): 1.12-1.18 (nz 12)
    and 2.16-2.28 (nz 24) iterations, and 0.75-0.83 (12), 1.04-1.13 (24),
    1.48-1.66 (36). A model, not a timing: the steps stay the same on
    every machine."""
    a = model.arrays
    points = float(np.count_nonzero(a.pw) + np.count_nonzero(a.rigid_mass)) / max(model.n_joints, 1)
    return 0.4 + nz * (0.025 + 0.02 * points)


class ReducedThetaIntegrator(StepLoop):
    """The theta-method step of :class:`ThetaIntegrator` for a robot whose
    velocities lie on a basis, ``v = B w`` (variable-strain segments:
    :attr:`mechanism.Mechanism.basis`, ``q = q0 + B z``): the step's
    residual R(v1) (:mod:`integrators`) projected on the basis, ``B^T R(B w1)
    = 0`` (Galerkin: the virtual power of the step's forces on the basis's
    motions), by Newton with the stiff part of the matrix,
    ``B^T (M + theta h D + (theta h)^2 K) B`` (the mass matrix in z at a step's first
    iterate; the small nz x nz matrix checked positive definite and
    inverted, held for the next steps while it serves, refreshed when the
    iteration slows), as the O(n) iteration does in q: compiled,
    :func:`reduced_steps`, the converged steps of a call in
    one kernel call. The positions stay on the basis: ``q1 = q0 (+) h v_t``
    adds on the soft and 1-dof joints and moves a spherical or free
    joint's quaternion on its group (its velocity coordinates are identity
    columns of B). A step that does not converge is tried again from v0
    with a fresh matrix, then by full Newton, then split into halves (down
    to ``max_substep_levels``: :meth:`_advance`). Same interface as
    :class:`ThetaIntegrator` (``run``, ``step``, ``last_a``,
    ``iterations``, ``factorisations``).

    ``prescribed``: (velocity indices, position indices) of
    position-controlled 1-dof joints (identity columns of B), eliminated:
    ``command`` (q_cmd, v_cmd or None) sets their end-of-step position,
    the Newton runs over the other coordinates, and ``efforts`` are their
    residual rows, the efforts that hold them (as the engine's compiled
    step does)."""

    def __init__(self, model, ws, act, inputs, dt, B, K, D, theta=0.5, tol=1e-4, max_iterations=10,
                 max_substep_levels=4, prescribed=None):
        self.model, self.ws, self.act, self.inputs = model, ws, act, inputs
        self.B = np.ascontiguousarray(B, dtype=float)
        self.BT = np.ascontiguousarray(self.B.T)
        self.K_z, self.D_z = self.BT @ K @ self.B, self.BT @ D @ self.B
        self.dt, self.theta, self.tol = float(dt), float(theta), float(tol)
        self.max_iterations, self.max_substep_levels = int(max_iterations), int(max_substep_levels)
        self.last_a = np.zeros(model.nv)
        self._prev_a = None           # the acceleration before last_a (None: fewer than two real steps)
        self._steps = 0               # steps taken
        self.factorisations = 0
        self.iterations = 0
        self._held_h = None           # the step whose Newton matrix self.arrays.Ainv holds
        self._fresh_iterations = 0.0  # the iterations of the last step that made its matrix (reduced_steps)
        self.refresh_cost = matrix_cost(model, self.B.shape[1])
        pv, pq = (np.asarray(a, dtype=np.int64) for a in (prescribed or ((), ())))
        self._pv, self._pq = pv, pq
        nz = self.B.shape[1]
        cols = np.array([int(np.flatnonzero(self.B[k])[0]) for k in pv], dtype=np.int64)
        self._pz, self._fz = cols, np.setdiff1d(np.arange(nz), cols)
        fixed = np.zeros(nz, dtype=np.bool_)
        fixed[cols] = True
        projector = np.linalg.solve(self.BT @ self.B, self.BT)     # least squares onto the basis
        self.arrays = BasisArrays.of(self.B, self.BT, projector, self.D_z, self.K_z, fixed, pv, pq, cols,
                                     np.eye(nz), np.zeros(nz), np.zeros(len(pv)))
        self.command = (np.zeros(len(pv)), None)
        self.efforts = np.zeros(len(pv))

    def newton_matrix(self, q, h):
        """``B^T (M(q) + theta h D + (theta h)^2 K) B`` (nz, nz): the
        matrix :func:`basis_newton_matrix` inverts."""
        th = self.theta * h
        return self.BT @ alg.crba(self.model, self.ws, q) @ self.B + th * self.D_z + th * th * self.K_z

    def full_matrix(self, q, v, a, g, h):
        """``B^T (M + theta h dtau/dv + (theta h)^2 dtau/dq) B`` (nz, nz) at
        (q, v, a): the velocity products and gravity's geometric terms in
        the matrix (:func:`algorithms.rnea_derivatives`; the loads' and
        tendons' geometric terms left out, as in
        :meth:`ThetaIntegrator._newton_full`)."""
        th = self.theta * h
        dq, dv = alg.rnea_derivatives(self.model, self.ws, q, v, a, g)
        A = alg.crba(self.model, self.ws, q) + th * dv + th * th * dq
        return self.BT @ A @ self.B

    def _kernel_steps(self, q, v, a_last, a_prev, have_prev, h, n, inputs, fresh=False):
        """:func:`reduced_steps`: up to n steps of h from (q, v) (updated
        in place, with a_last and a_prev) with the held Newton matrix when
        it is of this h (``fresh``: a new one regardless). Returns (steps
        done, their iterations, the failed step's status)."""
        loads, g, coef, effort = inputs
        q_cmd, v_cmd = self.command
        if not self._pv.size:
            q_cmd = v_cmd = _NO_COMMAND
        elif v_cmd is None:
            v_cmd = _NO_COMMAND
        stats = np.zeros(5)
        stats[4] = self._fresh_iterations
        fresh = fresh or self._held_h != h
        self._held_h = None              # until the kernel says what it left
        k = reduced_steps(self.ws.m, self.ws.w, self.act, loads, g, coef, effort, q, v, a_last, a_prev, have_prev,
                          self._steps, h, self.theta, self.tol, self.max_iterations, n, self.arrays,
                          np.asarray(q_cmd, dtype=float), np.asarray(v_cmd, dtype=float), fresh, self.refresh_cost,
                          stats)
        self._fresh_iterations = stats[4]
        if stats[2] == 1.0:
            self._held_h = h
        self.factorisations += int(stats[1])
        if k > 0 and self._pv.size:
            self.efforts = self.arrays.efforts.copy()
        return k, int(stats[0]), int(stats[3])

    def _newton(self, q0, v0, h, inputs, extrapolate=True):
        """(q1, v1, iterations) of one step of h, or None: from the Newton
        matrix held from an earlier step of this h (modified Newton: results
        to the tolerance), a fresh one when the iteration slows
        (``extrapolate`` False: from v0, with a fresh matrix)."""
        q, v = np.array(q0, dtype=float), np.array(v0, dtype=float)
        a = np.array(self.last_a, dtype=float) if extrapolate else np.zeros_like(v)
        have_prev = extrapolate and self._prev_a is not None and h == self.dt     # (not in sub-steps)
        a_prev = np.array(self._prev_a if have_prev else a, dtype=float)
        k, it, _ = self._kernel_steps(q, v, a, a_prev, have_prev, h, 1, inputs, fresh=not extrapolate)
        return (q, v, it) if k == 1 else None

    def _newton_full(self, q0, v0, h, inputs):
        """Full Newton from v0, the matrix :meth:`full_matrix` at every
        iterate (the fallback of :meth:`_advance`), or None."""
        loads, g, coef, effort = inputs
        ws, th = self.ws, self.theta * h
        R, qt = np.empty(self.model.nv), np.empty_like(q0)
        w1 = self.arrays.P @ v0              # the rates on the basis nearest v0 (least squares)
        pv, pz, fz = self._pv, self._pz, self._fz
        if pv.size:                  # the prescribed joints reach their commands at the end of the step
            w1[pz] = ((self.command[0] - q0[self._pq]) / h - (1 - self.theta) * v0[pv]) / self.theta
        floor = 1e-14 * max(1.0, np.abs(q0).max()) / h      # the round-off of q (as run_steps' floor)
        dw = np.zeros_like(w1)
        for it in range(1, self.max_iterations + 1):
            v1 = self.B @ w1
            vt = (1.0 - self.theta) * v0 + self.theta * v1
            integrate_pass(ws.m, q0, vt, th, qt)
            try:
                inverse = np.linalg.inv(self.full_matrix(qt, vt, (v1 - v0) / h, g, h)[np.ix_(fz, fz)])
            except np.linalg.LinAlgError:
                return None
            residual_pass(ws.m, ws.w, self.act, loads, g, coef, effort, qt, vt, (v1 - v0) / h, R, False)
            if not np.all(np.isfinite(R)):
                return None
            r = self.BT @ R
            dw[fz] = inverse @ (-h * r[fz])
            w1 = w1 + dw
            if np.max(np.abs(self.B @ dw)) <= max(self.tol * max(np.abs(v1).max(), np.abs(v0).max()), floor):
                v1 = self.B @ w1
                q1 = np.empty_like(q0)
                integrate_pass(ws.m, q0, (1.0 - self.theta) * v0 + self.theta * v1, h, q1)
                if pv.size:          # their efforts; their velocity the command's, or the step's change
                    self.efforts = r[pz].copy()
                    v_cmd = self.command[1]
                    v1[pv] = v_cmd if v_cmd is not None else (q1[self._pq] - q0[self._pq]) / h
                return q1, v1, it
        return None

    def _compiled_steps(self, inputs, q, v, a_last, a_prev, have_prev, n):
        """:meth:`StepLoop._compiled_steps`: :func:`reduced_steps` of step dt."""
        return self._kernel_steps(q, v, a_last, a_prev, have_prev, self.dt, n, inputs)

    def _advance(self, q0, v0, t, h, level, failed=None):
        """One step of h: Newton from the held matrix (``failed`` not None:
        already tried, by :meth:`run`'s compiled loop); if it fails, from v0 with a
        fresh one (after a violent step the last acceleration extrapolates
        far off), then full Newton from v0 (fast motions: the velocity
        products the matrix leaves out matter; not with the Cayley map,
        whose derivatives the engine does not have); then two halves, down
        to ``max_substep_levels``."""
        inputs = self.inputs(t + self.theta * h)
        out = None if failed is not None else self._newton(q0, v0, h, inputs)
        if out is None:
            out = self._newton(q0, v0, h, inputs, extrapolate=False)
        if out is None and not np.any(self.ws.arrays.kmap != 0):
            out = self._newton_full(q0, v0, h, inputs)
        if out is None and level < self.max_substep_levels:
            half = self._advance(q0, v0, t, 0.5 * h, level + 1)
            if half is not None:
                rest = self._advance(half[0], half[1], t + 0.5 * h, 0.5 * h, level + 1)
                if rest is not None:
                    return rest[0], rest[1], half[2] + rest[2]
        return out
