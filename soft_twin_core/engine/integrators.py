"""Time integration of the multibody engine: the implicit theta-method.

One step of size h solves, for the velocity v1 at t + h,

    R(v1) = ID(q_t, v_t, (v1 - v0)/h) + K (q_t - q0) + D v_t - tau_act(q_t, u) - effort = 0,
    v_t = (1 - theta) v0 + theta v1,   q_t = q0 (+) theta h v_t,   q1 = q0 (+) h v_t

(ID: inverse dynamics by RNEA with gravity and the external loads; (+):
integration on each joint's group). theta = 1/2 is the implicit midpoint
rule (second order, no numerical damping), theta = 1 implicit Euler
(first order, L-stable). Newton's matrix ``h dR/dv1`` is
``M + theta h D + (theta h)^2 K`` plus the geometric terms of the loads
and the velocity products; the iteration uses the first part, whose
articulated-body factorisation costs O(n) and whose solve is O(n)
(:func:`kernels.passes.aba_factor`): the stiff part of the problem
(elasticity, damping, inertia) is exact, the rest converges linearly at a
rate O((h omega)^2) for the soft geometric modes. A factorisation is made
at a step's first iterate, from the poses the residual's forward pass has
just computed (about one residual's cost): a fresh matrix contracts the
error 100-1000-fold per iteration on the benchmark cantilever. Both the
compiled multi-step path (:func:`run_steps`) and the single step keep it
for the next steps, also across calls, while the last step took two
iterations and contracted at least 100-fold (``REUSE_MAX_RATIO``), and
take a fresh one when a step with it does not converge: on the benchmark
cantilever one factorisation serves 3-7 steps (10 sections at 2 ms: 168
for 500 steps, 2.2 iterations a step instead of 2.0; 40 sections at 1 ms:
296 for 1000), 10-25 % less CPU per simulated second. A step that fails
is split into halves.

The whole Newton loop of a step runs compiled (one call per step).
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.forces import actuation_pass
from soft_twin_core.engine.joint_kinds import FREE, SPHERICAL
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.spatial import FALSE, _exp_into, _jit, _jit_inner, _jit_inline


@_jit_inner
def _quat_mul_into(a, b, out):
    ax, ay, az, aw = a[0], a[1], a[2], a[3]
    bx, by, bz, bw = b[0], b[1], b[2], b[3]
    out[0] = aw * bx + ax * bw + ay * bz - az * by
    out[1] = aw * by - ax * bz + ay * bw + az * bx
    out[2] = aw * bz + ax * by - ay * bx + az * bw
    out[3] = aw * bw - ax * bx - ay * by - az * bz


@_jit
def integrate_pass(m, q, v, h, out):
    """out = q (+) h v on each joint's group (quaternion exponential of the
    body angular velocity for spherical joints, SE(3) exponential of the
    body twist for free joints, addition otherwise)."""
    n = m.parent.shape[0]
    for k in range(q.shape[0]):
        out[k] = q[k]
    dq = np.empty(4)
    tmp = np.empty(4)
    x6 = np.zeros(6)
    E = np.empty((4, 4))
    for i in range(n):
        iq, iv, kind = m.iq[i], m.iv[i], m.kind[i]
        if kind == SPHERICAL or kind == FREE:
            o = 3 if kind == FREE else 0
            wv = 3 if kind == FREE else 0
            w0, w1, w2 = h * v[iv + wv], h * v[iv + wv + 1], h * v[iv + wv + 2]
            t = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            s = 0.5 - t * t / 48.0 if t < 1e-6 else np.sin(0.5 * t) / t
            dq[0], dq[1], dq[2], dq[3] = s * w0, s * w1, s * w2, np.cos(0.5 * t)
            if kind == FREE:
                # translation: p + R (T_so3(w)^T h v_lin), from exp_se3 of the body twist
                for a in range(6):
                    x6[a] = h * v[iv + a]
                _exp_into(x6, E)
                qx, qy, qz, qw = q[iq + 3], q[iq + 4], q[iq + 5], q[iq + 6]
                R = np.empty((3, 3))
                R[0, 0] = 1 - 2 * (qy * qy + qz * qz)
                R[0, 1] = 2 * (qx * qy - qz * qw)
                R[0, 2] = 2 * (qx * qz + qy * qw)
                R[1, 0] = 2 * (qx * qy + qz * qw)
                R[1, 1] = 1 - 2 * (qx * qx + qz * qz)
                R[1, 2] = 2 * (qy * qz - qx * qw)
                R[2, 0] = 2 * (qx * qz - qy * qw)
                R[2, 1] = 2 * (qy * qz + qx * qw)
                R[2, 2] = 1 - 2 * (qx * qx + qy * qy)
                for a in range(3):
                    out[iq + a] = q[iq + a] + R[a, 0] * E[0, 3] + R[a, 1] * E[1, 3] + R[a, 2] * E[2, 3]
            _quat_mul_into(q[iq + o:iq + o + 4], dq, tmp)
            nrm = np.sqrt(tmp[0] ** 2 + tmp[1] ** 2 + tmp[2] ** 2 + tmp[3] ** 2)
            for a in range(4):
                out[iq + o + a] = tmp[a] / nrm
        else:
            for a in range(m.nv[i]):
                out[iq + a] = q[iq + a] + h * v[iv + a]


def integrate_jacobians(model, v, h):
    """(E, J) (nv, nv): the derivatives of ``q1 = q (+) h v``
    (:func:`integrate_pass`) in the right-trivialised perturbations of the
    joints' groups (``q (+) d``: ``g exp(d)`` on a spherical or free joint,
    addition otherwise, the convention of
    :func:`algorithms.rnea_derivatives`): ``d1 = E d + h J dv``. On a
    group joint with ``x = h v`` (its body angular velocity, or twist
    ``[v; w]``) ``g exp(d) exp(x) = g exp(x) exp(Ad(exp(-x)) d)``, so
    ``E = Ad(exp(-x))`` (the rotation ``exp(-x)`` on SO(3)), and
    ``exp(x + h dv) = exp(x) exp(T(x) h dv)`` with T the right tangent
    operator (:func:`lie.T_so3`, :func:`lie.T_se3`); identities elsewhere."""
    nv = model.nv
    E, J = np.eye(nv), np.eye(nv)
    for i, joint in enumerate(model.joints):
        if joint.kind not in (SPHERICAL, FREE):
            continue
        iv = model.idx_v[i]
        x = h * np.asarray(v[iv:iv + joint.nv], dtype=float)
        if joint.kind == SPHERICAL:
            E[iv:iv + 3, iv:iv + 3] = lie.exp_so3(-x)
            J[iv:iv + 3, iv:iv + 3] = lie.T_so3(x)
        else:
            E[iv:iv + 6, iv:iv + 6] = lie.Ad_inv(lie.exp_se3(x))
            J[iv:iv + 6, iv:iv + 6] = lie.T_se3(x)
    return E, J


@_jit
def residual_pass(m, w, act, ld, g, coef, effort, q, v, a, out, at_rest):
    """out = ID(q, v, a) + K (q - q0) + D v - tau_act - effort (``at_rest``:
    v = a = 0, only the poses are computed)."""
    passes.forward_pass(m, w, q, v, a, 0 if at_rest else 2)
    residual_after_forward(m, w, act, ld, g, coef, effort, q, v, out, at_rest)


@_jit_inline
def residual_after_forward(m, w, act, ld, g, coef, effort, q, v, out, at_rest):
    """:func:`residual_pass` after its forward pass (the workspace's last,
    at (q, v, a))."""
    passes.rnea_pass(m, w, ld, g, out, at_rest)
    passes.joint_forces(m, q, v, out)
    for k in range(out.shape[0]):
        out[k] = -out[k]
    actuation_pass(m, w, act, coef, out)
    for k in range(out.shape[0]):
        out[k] = -out[k] - effort[k]


@_jit_inline
def newton_step(m, w, act, ld, g, coef, effort, q0, v0, v1, h, theta, tol, floor, max_it, q1, refactor):
    """Newton iteration of one theta-method step from (q0, v0), starting at
    the guess v1 (updated in place); q1 receives q0 (+) h v_t. ``refactor``:
    Newton's matrix is factorised at the first iterate, else the workspace's
    last factorisation (same h, an earlier state) is reused. Returns
    (iterations, status, ratio): status 0 converged, 1 not in max_it, 2
    diverging, 3 non-finite, 4 factorisation failed; ratio: the last update
    over the one before (0 after a single iteration), the contraction that
    tells a caller whether a reused factorisation still serves."""
    nv = v0.shape[0]
    vt = np.empty(nv)
    qt = np.empty(q0.shape[0])
    acc = np.empty(nv)
    R = np.empty(nv)
    dv = np.empty(nv)
    prev = -1.0
    rate = 0.0
    ratio = 0.0
    th = theta * h
    for it in range(1, max_it + 1):
        for k in range(nv):
            vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
            acc[k] = (v1[k] - v0[k]) / h
        integrate_pass(m, q0, vt, th, qt)
        residual_pass(m, w, act, ld, g, coef, effort, qt, vt, acc, R, FALSE)
        if it == 1 and refactor:
            # the residual's forward pass left the poses and subspaces at qt
            if not passes.aba_factor(m, w, th, th * th):
                return it, 4, ratio
        for k in range(nv):
            R[k] = -h * R[k]
        passes.aba_solve(m, w, R, dv)
        upd = 0.0
        vmax = 0.0
        finite = True
        for k in range(nv):
            v1[k] += dv[k]
            if not np.isfinite(dv[k]):
                finite = False          # (max() would drop a NaN)
            upd = max(upd, abs(dv[k]))
            vmax = max(vmax, abs(v1[k]), abs(v0[k]))
        if not finite:
            return it, 3, ratio
        goal = max(tol * vmax, floor)
        if prev > 0.0:
            ratio = upd / prev
        done = upd <= goal
        if not done and prev > 0.0:
            # Hairer-Wanner stopping rule: remaining error ~ r/(1 - r) * update
            if ratio < 0.5 and ratio / (1.0 - ratio) * upd <= goal:
                done = True
            elif upd > 100.0 * goal:
                rate = max(rate, ratio)
                if rate > 0.9:
                    return it, 2, ratio
        if done:
            for k in range(nv):
                vt[k] = (1.0 - theta) * v0[k] + theta * v1[k]
            integrate_pass(m, q0, vt, h, q1)
            return it, 0, ratio
        prev = upd
    return max_it, 1, ratio


@_jit_inline
def accept_step(q, v, a_last, a_prev, q1, v1, h):
    """A converged step's end (q1, v1) into (q, v) in place, its mean
    acceleration (v1 - v) / h into a_last and the one before into a_prev
    (the predictor's two real steps): the compiled step loops' end of a
    step."""
    for k in range(v.shape[0]):
        a_prev[k] = a_last[k]
        a_last[k] = (v1[k] - v[k]) / h
        v[k] = v1[k]
    for k in range(q.shape[0]):
        q[k] = q1[k]


# Reuse of Newton's factorisation across steps (run_steps, which the single
# step calls too): the matrix M + theta h D + (theta h)^2 K moves
# slowly with the state, so a step may iterate with an earlier step's
# factorisation while that one still contracts Newton's error as a fresh one
# does. A fresh factorisation is taken when the workspace holds none of this
# integrator for this h (Workspace.factor_key), after a step that needed more
# than two iterations or whose last contraction ratio exceeded
# REUSE_MAX_RATIO, and whenever a step with the reused one does not converge
# (the step is then retried from the same predictor, after at most three
# iterations with the reused one). With a fresh factorisation the ratio is
# 1e-3 - 1e-2 on the benchmark cantilever; two iterations meet the default
# tolerance while it stays below ~0.02.
REUSE_MAX_RATIO = 0.01


@_jit
def run_steps(m, w, act, ld, g, coef, effort, q, v, a_last, a_prev, have_prev, steps_before, h, theta, tol, max_it,
              n, fresh, max_ratio, stats):
    """Up to n theta-method steps with constant inputs in one call: q, v,
    a_last, a_prev advance in place after every converged step (predictor as
    :meth:`ThetaIntegrator._newton`: it extrapolates from two real steps,
    never from the initial zero acceleration; ``steps_before``: steps the
    integrator had taken before this call). Stops at the first step that does not
    converge, leaving it to the caller as it was before the attempt. Returns
    the number of steps done; stats[0] += Newton iterations, stats[1] +=
    factorisations, stats[2] = 1 if the workspace's factorisation (of step
    h) may serve the next step, else 0; stats[3] = the Newton status of a
    step that failed (newton_step's). ``fresh``: factorise at the first
    step (False: the workspace holds this integrator's factorisation of
    step h, which served its last step); ``max_ratio``: the contraction
    ratio up to which a factorisation is kept for the next step
    (REUSE_MAX_RATIO; negative: a fresh one every step)."""
    nv = v.shape[0]
    v1 = np.empty(nv)
    v_pred = np.empty(nv)
    q1 = np.empty(q.shape[0])
    stats[2] = 0.0
    for s in range(n):
        fin = True
        for k in range(nv):
            pred = (2.0 * a_last[k] - a_prev[k]) if have_prev else a_last[k]
            v1[k] = v[k] + h * pred
            if not np.isfinite(v1[k]):
                fin = False
        if not fin:
            for k in range(nv):
                v1[k] = v[k]
        qmax = 1.0
        for k in range(q.shape[0]):
            qmax = max(qmax, abs(q[k]))
        floor = 1e-14 * qmax / h
        for k in range(nv):
            v_pred[k] = v1[k]
        while True:                     # one call site: newton_step is inlined
            # a reused factorisation gets three iterations (a fresh one costs about one residual more)
            it, status, ratio = newton_step(m, w, act, ld, g, coef, effort, q, v, v1, h, theta, tol, floor,
                                            max_it if fresh else min(max_it, 3), q1, fresh)
            if fresh:
                stats[1] += 1
            if status == 0:
                break
            if fresh:
                # hand the step back as it was before this attempt: the caller
                # replays it through the single-step path (fallback, sub-steps)
                stats[3] = status
                return s
            stats[2] = 0.0
            # the reused factorisation does not serve here: a fresh one from the same predictor
            stats[0] += it
            fresh = True
            for k in range(nv):
                v1[k] = v_pred[k]
        stats[0] += it
        fresh = it > 2 or ratio > max_ratio
        stats[2] = 0.0 if fresh else 1.0
        accept_step(q, v, a_last, a_prev, q1, v1, h)
        have_prev = steps_before + s > 0
    return n


@dataclass
class StepInfo:
    """Newton iterations of the last step (all sub-steps) and whether it converged."""
    iterations: int
    converged: bool
    update: float


class StepLoop:
    """``run`` and ``step`` of the theta integrators (:class:`ThetaIntegrator`
    and :class:`reduced_step.ReducedThetaIntegrator`): the converged steps
    of a run in one compiled call, a step that needs more (a fallback,
    sub-steps) through :meth:`step`, and the accelerations the predictor
    extrapolates (``last_a``; ``_prev_a`` from two real steps only, never
    from the initial zero acceleration). A subclass sets ``dt``,
    ``inputs``, ``max_iterations``, ``last_a``, ``_prev_a = None``,
    ``_steps = 0`` (steps taken), ``iterations = 0``, and gives
    ``_compiled_steps(inputs, q, v, a_last, a_prev, have_prev, n)`` ->
    (steps done, Newton iterations, the failed step's status; q, v, a_last,
    a_prev advanced in place) and ``_advance(q0, v0, t, h, level, failed)``
    (one step of h with its fallbacks; ``failed``: the status of the
    compiled attempt at this very step, already made, or None)."""

    def run(self, state, n):
        """n steps with inputs that do not change in time (``inputs`` is
        called once), the converged ones in one compiled call; a step that
        needs more goes through :meth:`step`. Returns the StepInfo of the
        last step taken."""
        inputs = self.inputs(state.t)
        info = StepInfo(0, True, 0.0)
        done = 0
        while done < n:
            q = np.array(state.q, dtype=float)
            v = np.array(state.qdot, dtype=float)
            a_last = np.array(self.last_a, dtype=float)
            have_prev = self._prev_a is not None and self._steps > 0
            a_prev = np.array(self._prev_a if have_prev else a_last, dtype=float)
            k, it, status = self._compiled_steps(inputs, q, v, a_last, a_prev, have_prev, n - done)
            self.iterations += it
            if k > 0:
                state.q, state.qdot, state.t = q, v, state.t + k * self.dt
                self.last_a = a_last
                self._prev_a = a_prev if self._steps + k > 1 else None   # as step(): two real steps
                self._steps += k
                done += k
                info = StepInfo(it // k, True, 0.0)
            if done < n:
                info = self.step(state, failed=status)
                if not info.converged:
                    return info
                done += 1
        return info

    def step(self, state, failed=None):
        """One step of dt from ``state`` (updated in place when it converges);
        ``failed``: see :meth:`_advance`."""
        out = self._advance(np.asarray(state.q, dtype=float), np.asarray(state.qdot, dtype=float), state.t,
                            self.dt, 0, failed)
        if out is None:
            return StepInfo(self.max_iterations, False, np.inf)
        q1, v1, it = out
        self.iterations += it
        # the predictor extrapolates from two real steps only (not from the initial zeros)
        self._prev_a = self.last_a if self._steps > 0 else None
        self._steps += 1
        self.last_a = (v1 - state.qdot) / self.dt
        state.q, state.qdot, state.t = q1, v1, state.t + self.dt
        return StepInfo(it, True, 0.0)


class ThetaIntegrator(StepLoop):
    """Fixed-step theta-method on a multibody model and its workspace.

    ``full_newton``: when the O(n) iteration fails even in sub-steps, try a
    full Newton with the analytic derivatives (dense, O(n^3)).
    ``inputs(t)`` returns ``(loads, gravity, coef, effort)``: LoadArrays, the
    gravity vector, the actuator coefficients ``act.unit @ u`` and the
    generalised effort (nv,) of actuated joints, at time t. The state (q, v,
    t) is plain and owned by the caller's ``state`` object (attributes q,
    qdot, t), updated only by converged steps.
    """

    def __init__(self, model, ws, act, inputs, dt, theta=0.5, tol=1e-4, max_iterations=10,
                 max_substep_levels=4, full_newton=True, reuse_factorisation=True):
        self.model, self.ws, self.act, self.inputs = model, ws, act, inputs
        self.dt = float(dt)
        self.theta = float(theta)
        self.tol = float(tol)
        self.max_iterations = int(max_iterations)
        self.max_substep_levels = int(max_substep_levels)
        self.full_newton = bool(full_newton)   # the dense fallback of _newton_full
        self._token = object()                 # names this integrator in ws.factor_key
        # keep Newton's factorisation across steps while it serves (REUSE_MAX_RATIO); False: a fresh one every step
        self.max_ratio = REUSE_MAX_RATIO if reuse_factorisation else -1.0
        self.last_a = np.zeros(model.nv)
        self._prev_a = None
        self._steps = 0
        self.factorisations = 0
        self.iterations = 0           # Newton iterations so far (all steps)

    def _run_steps(self, inputs, q, v, a_last, a_prev, have_prev, h, n, stats):
        """:func:`run_steps` of n steps of size h on this integrator's
        workspace, reusing the factorisation it holds when it is this
        integrator's of this h (``Workspace.factor_key``) and recording what
        it leaves; counts the factorisations. Returns the steps done."""
        loads, g, coef, effort = inputs
        key = (self._token, h)
        reuse = self.ws.factor_key == key
        self.ws.factor_key = None         # until run_steps says what it left
        k = run_steps(self.ws.m, self.ws.w, self.act, loads, g, coef, effort, q, v, a_last, a_prev, have_prev,
                      self._steps, h, self.theta, self.tol, self.max_iterations, n, not reuse, self.max_ratio, stats)
        if stats[2] == 1.0:
            self.ws.factor_key = key
        self.factorisations += int(stats[1])
        return k

    def _newton(self, q0, v0, t, h):
        """One step of size h from (q0, v0), inputs at t + theta h: (q1, v1,
        iterations) or None, and the Newton status (0 converged, 3 non-finite, ...)."""
        q = np.array(q0, dtype=float)
        v = np.array(v0, dtype=float)
        a_last = np.array(self.last_a, dtype=float)
        have_prev = self._prev_a is not None and h == self.dt          # linear extrapolation
        a_prev = np.array(self._prev_a if have_prev else a_last, dtype=float)
        stats = np.zeros(4)
        if self._run_steps(self.inputs(t + self.theta * h), q, v, a_last, a_prev, have_prev, h, 1, stats) == 0:
            return None, int(stats[3])
        return (q, v, int(stats[0])), 0

    def _newton_full(self, q0, v0, h, inputs, v1):
        """Fallback when the O(n) iteration does not converge (large strain
        rates: the geometric terms it leaves out matter): Newton with the
        dense matrix ``M + theta h dtau/dv + (theta h)^2 dtau/dq`` from the
        analytic derivatives of inverse dynamics (loads' and tendons'
        geometric terms left out), refreshed every iteration."""
        loads, g, coef, effort = inputs
        model, ws, th = self.model, self.ws, self.theta * h
        if np.any(ws.arrays.kmap != 0):
            return None
        nv = model.nv
        R = np.empty(nv)
        qt = np.empty_like(q0)
        v1 = np.array(v1, dtype=float)
        for it in range(1, 4 * self.max_iterations + 1):
            vt = (1.0 - self.theta) * v0 + self.theta * v1
            acc = (v1 - v0) / h
            integrate_pass(ws.m, q0, vt, th, qt)
            residual_pass(ws.m, ws.w, self.act, loads, g, coef, effort, qt, vt, acc, R, False)
            if not np.all(np.isfinite(R)):
                return None
            dq, dv = alg.rnea_derivatives(model, ws, qt, vt, acc, g)
            A = alg.crba(model, ws, qt) + th * dv + th * self.theta * h * dq
            try:
                dv1 = np.linalg.solve(A, -h * R)
            except np.linalg.LinAlgError:
                return None
            v1 += dv1
            if np.max(np.abs(dv1)) <= max(self.tol * max(np.abs(v1).max(), np.abs(v0).max()), 1e-300):
                vt = (1.0 - self.theta) * v0 + self.theta * v1
                q1 = np.empty_like(q0)
                integrate_pass(ws.m, q0, vt, h, q1)
                return q1, v1, it
        return None

    def _advance(self, q0, v0, t, h, level, failed=None):
        """One step of size h: the O(n) iteration; if it fails, two halves
        (down to ``max_substep_levels``); if they fail too, the dense full
        Newton at this h (``full_newton``; not for non-finite residuals). The
        halves come first: on the benchmark cantilever whipping after its
        fall (strain rates ~1e3/s) they cost 35-90 ms CPU per 0.1 s against
        200-900 ms for the dense fallback. ``failed``: the status of the
        O(n) iteration of this very step, already tried (by :meth:`run`'s
        compiled loop, which gives up on the same iterates): not repeated."""
        if failed is None:
            out, status = self._newton(q0, v0, t, h)
            if out is not None:
                return out
        else:
            status = failed
        if level < self.max_substep_levels:
            half = self._advance(q0, v0, t, 0.5 * h, level + 1)
            if half is not None:
                rest = self._advance(half[0], half[1], t + 0.5 * h, 0.5 * h, level + 1)
                if rest is not None:
                    return rest[0], rest[1], half[2] + rest[2]
        if self.full_newton and status != 3:
            loads, g, coef, effort = self.inputs(t + self.theta * h)
            return self._newton_full(q0, v0, h, (loads, g, coef, effort), v0 + h * self.last_a)
        return None

    def _compiled_steps(self, inputs, q, v, a_last, a_prev, have_prev, n):
        """:meth:`StepLoop._compiled_steps`: :func:`run_steps` of step dt."""
        stats = np.zeros(4)
        k = self._run_steps(inputs, q, v, a_last, a_prev, have_prev, self.dt, n, stats)
        return k, int(stats[0]), int(stats[3])
