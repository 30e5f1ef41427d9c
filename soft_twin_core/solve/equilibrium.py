"""Static equilibrium of a robot on the multibody engine, without
constraint rows: one Newton loop for a classic rod and for a tree whose
joints are soft, effort-controlled or passive (:mod:`constrained` adds the
closed chains and position-controlled joints as multipliers, and calls
:func:`solve` when a mechanism has none).

``R(q) = K (q - q0) + tau_rnea(q; loads, gravity) - tau_act(q, u) - effort = 0``
(:func:`integrators.residual_pass` at rest), its analytic tangent
(:func:`kernels.tangent.static_tangent_pass`, the stiffness, the tendons'
:func:`forces.actuation_tangent_pass`), Newton with a backtracking line
search, compiled in one call (:func:`kernels.static_newton.static_newton`)
up to ``COMPILED_NEWTON_MAX_DOF`` unknowns, else the same iterates in numpy
(:func:`newton_numpy`, also the tests' reference of the kernel). A tangent
from a nearby state (``Kt_hint``) serves the first steps. An equilibrium
whose tangent has a divergence mode (:func:`equilibrium_stability`) is
rejected in favour of the loaded path from the start point (continuation
in a load factor, also used when a full solve fails).
"""

import math

import numpy as np

from soft_twin_core.engine.forces import actuation_tangent_pass
from soft_twin_core.engine.integrators import residual_pass
from soft_twin_core.engine.kernels.data import LoadArrays
from soft_twin_core.engine.kernels.static_newton import static_newton
from soft_twin_core.engine.kernels.tangent import static_tangent_pass
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError

# Up to this many unknowns the compiled Newton (one call per solve) is used;
# above, the numpy loop, whose LAPACK solve is blocked: measured, the
# compiled elimination takes 73 / 491 / 7662 us at 60 / 120 / 240 unknowns,
# numpy 51 / 192 / 857 us, while the compiled loop saves ~0.1 ms of Python per
# iteration.
COMPILED_NEWTON_MAX_DOF = 96


class Problem:
    """The equilibrium equations of one tree under fixed inputs, bound to one
    workspace: actuator arrays ``act``, stiffness ``K`` (nv, nv), loads
    (LoadArrays, the point-moment tendons' moments included), gravity ``g``,
    tendon coefficients ``coef`` and joint efforts ``effort`` (nv,)."""

    def __init__(self, tree, act, K, loads, g, coef, effort=None):
        self.tree, self.ws, self.act = tree, Workspace(tree), act
        self.K, self.absK = K, np.abs(K)          # |K|: the round-off level of the residual
        self.loads, self.g, self.coef = loads, np.asarray(g, float), coef
        self.zeros = np.zeros(tree.nv)
        self.effort = self.zeros if effort is None else np.ascontiguousarray(effort, float)
        self.floor = load_scale(tree, loads, self.g, self.effort)
        self.n_tangents = 0                       # tangents computed (Newton's and tangent()'s)

    def scaled(self, t):
        """The same problem with every input times ``t`` (actuation, loads,
        gravity, efforts): the continuation's load factor."""
        ld = self.loads
        return Problem(self.tree, self.act, self.K, LoadArrays(ld.joint, ld.x, t * ld.wrench, ld.world),
                       t * self.g, t * self.coef, t * self.effort)

    @property
    def n(self):
        """The number of unknowns (the tree's velocity coordinates)."""
        return self.tree.nv

    @property
    def q0(self):
        """Where the unknowns are at the reference configuration."""
        return self.tree.q0

    def residual(self, q, loads=None):
        """R(q); the workspace then holds the forward pass and the RNEA
        wrenches at rest under ``loads`` (default the problem's): what
        :meth:`tangent` reads."""
        out = np.empty(self.tree.nv)
        residual_pass(self.ws.m, self.ws.w, self.act, self.loads if loads is None else loads, self.g, self.coef,
                      self.effort, np.ascontiguousarray(q, dtype=float), self.zeros, self.zeros, out, True)
        return out

    def tangent(self, q):
        """dR/dq, analytic: one forward and one RNEA pass (the residual's)
        and one O(n^2) tangent pass."""
        m, w = self.ws.m, self.ws.w
        self.n_tangents += 1
        self.residual(q)
        Kt = self.K.copy()
        static_tangent_pass(m, w, self.loads, self.g, Kt)
        actuation_tangent_pass(m, w, self.act, self.coef, Kt)
        return Kt


class ReducedProblem:
    """A :class:`Problem` in the coordinates z of ``q = q0 + B z`` (a robot
    with variable-strain segments, :attr:`mechanism.Mechanism.basis`): the
    principle of virtual work on the basis (Galerkin), residual ``B^T R(q0 +
    B z)``, tangent ``B^T K_t B``, stiffness ``B^T K B``. :func:`solve`
    takes it as it takes a Problem; its unknowns are z."""

    def __init__(self, full, B):
        self.full, self.B = full, np.asarray(B, dtype=float)
        self.K = self.B.T @ full.K @ self.B
        self.absK = np.abs(self.B).T @ full.absK @ np.abs(self.B)
        self.floor = full.floor
        self.q0 = np.zeros(self.B.shape[1])

    @property
    def n(self):
        return self.B.shape[1]

    @property
    def n_tangents(self):
        return self.full.n_tangents

    def q_of(self, z):
        """The robot's q at the coordinates z."""
        return self.full.q0 + self.B @ z

    def z_of(self, q):
        """The coordinates z nearest q (least squares: q itself when it lies on the basis)."""
        return np.linalg.lstsq(self.B, np.asarray(q, dtype=float) - self.full.q0, rcond=None)[0]

    def scaled(self, t):
        return ReducedProblem(self.full.scaled(t), self.B)

    def residual(self, z):
        return self.B.T @ self.full.residual(self.q_of(z))

    def tangent(self, z):
        return self.B.T @ self.full.tangent(self.q_of(z)) @ self.B


def load_scale(tree, loads, g, effort):
    """The size of the generalised forces the inputs can make [N m or N]:
    weight times the robot's size, external forces times the size, external
    moments, joint efforts. The floor of the residual's force scale: an arm
    held upright by a spring has no elastic force and no gravity torque at
    its equilibrium (the weight is carried by the structure), and relative
    to their round-off its residual would never converge."""
    mass, size = tree.mass_and_size
    w = loads.wrench
    scale = math.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]) * mass * size
    if w.shape[0]:
        scale += np.abs(w[:, :3]).sum() * size + np.abs(w[:, 3:]).sum()
    return scale + np.abs(effort).max(initial=0.0)


# ----------------------------------------------------------------------------
# Stability
# ----------------------------------------------------------------------------

def constraint_null_space(G, rtol=1e-10):
    """An orthonormal basis Z (nv, k) of the motions the constraints allow
    to first order (G Z = 0), from the SVD of G (redundant rows allowed)."""
    nv = G.shape[1]
    if G.shape[0] == 0:
        return np.eye(nv)
    _, sv, Vt = np.linalg.svd(G)
    rank = int(np.sum(sv > rtol * sv.max())) if sv.size and sv.max() > 0 else 0
    return Vt[rank:].T


def reduced_stiffness(Kt, Z):
    """Z^T Kt Z: the tangent stiffness dR/dq at fixed multipliers (the
    Hessian of the Lagrangian, the constraint forces' geometric stiffness
    included) on the constraints' allowed motions Z."""
    return Z.T @ Kt @ Z


def is_stable(Kt):
    """Static stability of an equilibrium without constraints: every
    eigenvalue of the tangent dR/dq has a positive real part (no divergence
    mode), to the round-off margin of :func:`equilibrium_stability`; a
    Cholesky factorisation decides a symmetric (conservative) tangent."""
    scale = max(np.abs(Kt).max(initial=0), 1e-300)
    if np.abs(Kt - Kt.T).max(initial=0) <= 1e-10 * scale:
        try:
            np.linalg.cholesky(0.5 * (Kt + Kt.T) + 1e-9 * scale * np.eye(len(Kt)))
            return True
        except np.linalg.LinAlgError:
            return False
    return bool(np.linalg.eigvals(Kt).real.min(initial=np.inf) > -1e-9 * scale)


def equilibrium_stability(Kt, G=None):
    """(stable, smallest eigenvalue) of an equilibrium: stable when the
    reduced stiffness on the constraints' allowed motions (all motions
    when ``G`` is None or empty) has no eigenvalue with a negative real part
    (second-order condition of the constrained energy minimum; a follower
    load's unsymmetric tangent: no divergence mode), to a round-off margin.
    The eigenvalue is in the generalised units of the allowed motions."""
    H = Kt if G is None or G.shape[0] == 0 else reduced_stiffness(Kt, constraint_null_space(G))
    if H.size == 0:
        return True, float("inf")
    scale = max(np.abs(H).max(), 1e-300)
    if np.abs(H - H.T).max() <= 1e-10 * scale:
        ev = np.linalg.eigvalsh(0.5 * (H + H.T))
    else:
        ev = np.linalg.eigvals(H).real
    lo = float(ev.min())
    return bool(lo > -1e-9 * scale), lo


# ----------------------------------------------------------------------------
# Newton
# ----------------------------------------------------------------------------

def force_scale(pb, q, R):
    """A force scale for the relative residual: the largest of the elastic
    force K (q - q0), the applied force K (q - q0) - R and the inputs'
    :func:`load_scale`."""
    Kq = pb.K @ (q - pb.q0)
    return max(np.abs(Kq).max(initial=0), np.abs(Kq - R).max(initial=0), pb.floor, 1e-300)


def converged(pb, q, R, scale, tol):
    """|R| <= tol scale + the round-off level 64 eps |K| (|q| + |q0|) of the
    stiff axial/shear modes (K (q - q0) cancels terms of size |K| |q|)."""
    roundoff = 64 * np.finfo(float).eps * (pb.absK @ (np.abs(q) + np.abs(pb.q0)))
    return bool(np.all(np.abs(R) <= tol * scale + roundoff))


def newton(pb, q, tol, max_iterations, Kt_hint=None):
    """Newton with line search on ``pb`` from q. With ``Kt_hint`` (a tangent
    from a nearby state) the first steps reuse it (modified Newton) while
    each step cuts the residual at least tenfold; then fresh tangents; a
    converged solve takes one more (polish) step with the last tangent when
    it lowers |R|. Compiled up to ``COMPILED_NEWTON_MAX_DOF`` unknowns, else
    :func:`newton_numpy` (the same iterates). Returns (q, R, iterations,
    converged, the last tangent used: the hint object itself, a fresh array,
    or None)."""
    n = pb.n
    if n > COMPILED_NEWTON_MAX_DOF or isinstance(pb, ReducedProblem):
        return newton_numpy(pb, np.array(q, dtype=float), tol, max_iterations, Kt_hint)
    use_hint = Kt_hint is not None and Kt_hint.shape == (n, n)
    q = np.array(q, dtype=float)
    Kt, R = np.empty((n, n)), np.empty(n)
    hint = np.ascontiguousarray(Kt_hint, dtype=float) if use_hint else Kt
    it, ok, which, n_tangents = static_newton(pb.ws.m, pb.ws.w, pb.act, pb.loads, pb.g, pb.coef, pb.effort, pb.K,
                                              pb.absK, pb.tree.q0, q, float(tol), float(pb.floor), int(max_iterations), hint,
                                              use_hint, Kt, R)
    pb.n_tangents += n_tangents
    return q, R, int(it), bool(ok), (None, Kt_hint, Kt)[which]


def newton_numpy(pb, q, tol, max_iterations, Kt_hint=None):
    """:func:`newton` as a numpy loop (LAPACK solves): for large models,
    and the tests' reference of the compiled kernel."""
    R = pb.residual(q)
    scale = force_scale(pb, q, R)
    it, Kt = 0, None
    n = pb.n
    reuse = Kt_hint is not None and Kt_hint.shape == (n, n)
    for it in range(1, max_iterations + 1):
        if converged(pb, q, R, scale, tol):
            if Kt is not None:
                try:
                    q_p = q + np.linalg.solve(Kt, -R)
                    R_p = pb.residual(q_p)
                    if np.all(np.isfinite(R_p)) and np.linalg.norm(R_p) < np.linalg.norm(R):
                        q, R = q_p, R_p
                except np.linalg.LinAlgError:
                    pass
            return q, R, it - 1, True, Kt
        Kt = Kt_hint if reuse else pb.tangent(q)
        try:
            dq = np.linalg.solve(Kt, -R)
        except np.linalg.LinAlgError:
            if reuse:
                reuse = False
                continue
            return q, R, it, False, None
        step, r0 = 1.0, np.linalg.norm(R)
        for _ in range(20):
            q_try = q + step * dq
            R_try = pb.residual(q_try)
            if np.all(np.isfinite(R_try)) and np.linalg.norm(R_try) < (1 - 1e-4 * step) * r0:
                break
            step *= 0.5
        else:
            if reuse:              # the stale tangent gives no descent: take a fresh one
                reuse = False
                continue
            return q, R, it, converged(pb, q, R, scale, tol), Kt
        if reuse and (step < 1.0 or np.linalg.norm(R_try) > 0.1 * r0):
            reuse = False          # slow: fresh tangents from now on
        q, R = q_try, R_try
        scale = max(scale, force_scale(pb, q, R))
    return q, R, it, converged(pb, q, R, scale, tol), Kt


class Solution:
    """What :func:`solve` found: q, R (residual), iterations (Newton steps in
    all), load_steps, stable, min_stiffness_eigenvalue (nan when not
    checked), tangent (the last Newton tangent: a hint for the next solve)."""

    __slots__ = ("q", "R", "iterations", "load_steps", "stable", "min_stiffness_eigenvalue", "tangent")

    def __init__(self, q, R, iterations, load_steps, stable=True, lo=float("nan"), tangent=None):
        self.q, self.R, self.iterations, self.load_steps = q, R, iterations, load_steps
        self.stable, self.min_stiffness_eigenvalue, self.tangent = stable, lo, tangent


def solve(pb, q, *, tol=1e-10, max_iterations=50, max_load_steps=64, check_stability=True, tangent_hint=None,
          eigenvalue=False):
    """The equilibrium of ``pb`` from q: Newton from q; if it fails or lands
    on an unstable equilibrium (``check_stability``, :func:`is_stable`),
    continuation in the load factor from q, bisecting a failed increment.
    When no stable path exists the unstable equilibrium Newton found is
    returned, flagged. ``eigenvalue``: also report the tangent's smallest
    eigenvalue (:func:`equilibrium_stability`; an O(n^3) eigen-solve).
    Raises StaticsError with the reached load fraction."""
    q1, R, total, ok, Kt = newton(pb, q, tol, max_iterations, tangent_hint)
    steps, lo = 1, float("nan")
    fallback = None                     # a converged but unstable equilibrium
    if Kt is tangent_hint:
        Kt = None                       # judge stability (and hand on) a tangent of this state, not the hint
    if ok and check_stability:
        if Kt is None:
            Kt = pb.tangent(q1)
        if not is_stable(Kt):
            ok, fallback = False, (q1, R, equilibrium_stability(Kt)[1])     # (rare: its eigenvalue now)
    if not ok:
        t, dt, steps = 0.0, 0.25, 0
        q_c = q.copy()
        while t < 1.0:
            target = min(1.0, t + dt)
            pb_t = pb.scaled(target)
            q_try, R, it, ok, Kt = newton(pb_t, q_c, tol, max_iterations)
            total += it
            steps += 1
            if ok and check_stability:
                if Kt is None:
                    Kt = pb_t.tangent(q_try)
                ok = is_stable(Kt)
            if ok:
                t, q_c = target, q_try
                dt = min(2 * dt, 1.0)
            else:
                dt *= 0.5
                if dt < 1.0 / max_load_steps / 64 or steps > 4 * max_load_steps:
                    if fallback is not None:
                        return Solution(fallback[0], fallback[1], total, steps, False, fallback[2])
                    raise StaticsError(f"statics did not converge: reached load fraction {t:.4f}; "
                                       f"the load or actuation may exceed what the model can carry, "
                                       f"or the structure buckles (try a different start)")
        q1 = q_c
        R = pb.residual(q1)
    if eigenvalue and check_stability:
        lo = equilibrium_stability(Kt if Kt is not None else pb.tangent(q1))[1]
    return Solution(q1, R, total, steps, True, lo, Kt)
