"""Reference solutions for Cosserat-rod statics, independent of the PCS code.

Two references used to validate the piecewise-constant-strain (PCS) solver:

1. :func:`solve_cosserat_statics` -- the geometrically exact Cosserat
   (Simo-Reissner) rod of the slides, part A, for a uniform rod with a
   clamped base and a loaded free tip, solved as a two-point boundary value
   problem by multiple shooting (all segments integrated together by one
   ``scipy.integrate.solve_ivp`` call, DOP853, rtol 1e-12) with Newton's
   method on the base wrench and the segment start states. The Jacobian
   comes from the variational (sensitivity) equations integrated alongside
   the state; large loads are reached by adaptive load continuation
   (tangent, then cubic Hermite predictor, with a branch-following check).
   Simple shooting (one segment) is ill-conditioned for a rod in tension
   (perturbations grow like exp(L sqrt(T/EI))), hence the segments.
2. :func:`elastica_cantilever_tip` -- the inextensible, unshearable
   (Euler/Bernoulli) elastica cantilever under a dead transverse tip load in
   closed form with elliptic integrals (Bisshopp & Drucker, "Large deflection
   of cantilever beams", Q. Appl. Math. 3(3):272-275, 1945; tabulated by
   Mattiasson, "Numerical results from large deflection beam and frame
   problems analysed by means of elliptic integrals", Int. J. Numer. Meth.
   Eng. 17:145-153, 1981).

Conventions (docs/CONVENTIONS.md): 6-vectors are [linear; angular]; strain
``f = [f_u; f_w]`` and wrenches ``[force; moment]`` in the cross-section
(body) frame unless the name says ``_world``; ``H' = H hat6(f)``; the
cross-section stiffness ``K`` (6x6, e.g. ``diag(EA, G A2, G A3, G J, E I2,
E I3)``) acts on ``f - f0``. SI units.

Equations (derived here, not copied from the slides)
----------------------------------------------------
Let ``n(s), m(s)`` be the force and the moment (about the centre line point
``p(s)``), world axes, that the distal part ``(s, L]`` exerts on the proximal
part ``[0, s)`` across the section at ``s``. Equilibrium of the distal part
(tip force ``F``, tip moment ``M``, distributed force ``q`` per unit length):

    n(s) = F + int_s^L q ds'
    m(s) = M + (p(L) - p(s)) x F + int_s^L (p(s') - p(s)) x q ds'

hence ``n' = -q`` and ``m' = -p' x n``. The body-frame internal wrench is
``sigma = [R^T n; R^T m] = K (f - f0)`` (a positive bending moment about y
produces a positive curvature about y), and the kinematics are
``p' = R f_u``, ``R' = R hat(f_w)``. Boundary conditions: ``p(0), R(0)``
from the base pose; ``n(L) = F_dead + R(L) F_follower`` and
``m(L) = M_dead + R(L) M_follower``.

In body form, with ``g = [R^T q; 0]`` the applied distributed wrench per
unit length in the section frame, these equations read

    sigma' - ad(f)^T sigma + g = 0,

which agrees with the slides' dynamic strong form (part A,
``M eta_dot - ad_eta^T M eta - sigma' + ad_f^T sigma = g_ext`` with
``eta = 0``) for ``g_ext = g`` the applied load. The slides' static form
``sigma' - ad_f^T sigma = g_ext`` has the opposite sign of ``g_ext`` (a
typo, or ``g_ext`` meaning minus the load). Checked numerically in
test/test_continuum.py.

The wrench exerted by the support on the rod at ``s = 0`` is
``[-n(0); -m(0)]`` (world axes, moment about the base origin ``p(0)``).
"""

from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp
from scipy.linalg import expm
from scipy.optimize import brentq
from scipy.special import ellipe, ellipeinc, ellipkinc, ellipkm1

from soft_twin_core.errors import ContinuumConvergenceError

__all__ = ["ContinuumSolution", "solve_cosserat_statics", "elastica_cantilever_tip",
           "elastica_cantilever_tip_angle", "ContinuumConvergenceError"]


@dataclass
class ContinuumSolution:
    """Equilibrium of a Cosserat rod sampled on an arc-length grid.

    s : (N,) arc length [m], 0..L.
    poses : (N, 4, 4) world poses ``H(s)`` of the cross-sections.
    strains : (N, 6) body-frame strain ``f(s)`` = [f_u (1); f_w (1/m)].
    internal_wrench : (N, 6) body-frame ``sigma(s) = K (f - f0)`` = [N; N m]:
        the wrench the distal part exerts on the proximal part across the
        section at ``s`` (moment about the section origin). At the tip it
        equals the applied tip wrench expressed in the tip frame.
    internal_wrench_world : (N, 6) the same wrench in world axes
        ``[R n_b; R m_b]`` (moment about ``p(s)``).
    base_wrench_world : (6,) reaction [force (N); moment (N m)] exerted BY
        the support ON the rod at s = 0, world axes, moment about the base
        origin (the translation of ``base_pose``). Equals ``-internal_wrench_world[0]``.
        For equilibrium it cancels the applied loads:
        ``F_base + F_tip + q L = 0`` and
        ``M_base + M_tip + (p_L - p_0) x F_tip + int (p - p_0) x q ds = 0``.
    info : solver statistics (load steps, Newton iterations, failed (halved)
        steps, ODE integrations, shooting segments, final scaled residual).
    """
    s: np.ndarray
    poses: np.ndarray
    strains: np.ndarray
    internal_wrench: np.ndarray
    base_wrench_world: np.ndarray
    internal_wrench_world: np.ndarray = None
    info: dict = field(default_factory=dict)

    def tip_pose(self) -> np.ndarray:
        """World pose (4, 4) of the tip cross-section."""
        return self.poses[-1].copy()


# ----------------------------------------------------------------------------
# Cosserat rod: multiple shooting
# ----------------------------------------------------------------------------

def _cross(a, b):
    """a x b for broadcastable (..., 3) arrays."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack(np.broadcast_arrays(a1 * b2 - a2 * b1, a2 * b0 - a0 * b2,
                                        a0 * b1 - a1 * b0), axis=-1)


def _hat(w):
    """(..., 3) -> (..., 3, 3) skew matrix, hat(w) @ b = w x b."""
    out = np.zeros(w.shape + (3,))
    out[..., 0, 1] = -w[..., 2]
    out[..., 0, 2] = w[..., 1]
    out[..., 1, 0] = w[..., 2]
    out[..., 1, 2] = -w[..., 0]
    out[..., 2, 0] = -w[..., 1]
    out[..., 2, 1] = w[..., 0]
    return out


# hat(e_l), l = 0, 1, 2:  R @ hat(a) = sum_l a_l (R @ hat(e_l))
_HAT_BASIS = _hat(np.eye(3))

# A converging solve needs ~5-80 integrations (the gravity benchmark of
# docs/CONVENTIONS.md: ~35); this cap bounds the time spent on a hopeless case.
_MAX_SHOOTS = 400

_NS = 18          # state size: P (3), R (9, row-major), n (3), m (3)
_NC = _NS + 1     # sensitivity columns: the 18 initial states and lam


class _BudgetExceeded(ContinuumConvergenceError):
    """Too many ODE integrations: give up instead of halving the load step forever."""


class _Problem:
    """Nondimensional multiple-shooting problem.

    Scales: length L, force Fs = max(K_ww)/L^2, moment Fs L. Arc length
    t = s/L in [0, 1], split into M equal segments [t_k, t_k + 1/M]; all M
    segments are integrated together by one solve_ivp call in the local
    parameter tau in [0, 1] (t = t_k + tau/M), so their step counts are
    shared and the exponential growth of the shooting map (a rod in tension
    behaves like e^(L sqrt(T/EI))) is split into M small factors.

    State y = [P, R, n, m] with P = p/L, n = n/Fs, m = m/(Fs L), all in the
    base frame (R(0) = I, P(0) = 0). Dimensionless strain ft = S f with
    S = diag(1,1,1,L,L,L), wrench st = sigma / W, W = Fs diag(1,1,1,L,L,L):
    ft = S f0 + Ct st with Ct = S K^-1 W.

    Unknowns z = [n(0), m(0) (6); y_1 .. y_{M-1} (18 each)] (segment start
    states), equations: continuity y_k(end) = y_{k+1} and the tip boundary
    conditions. The load parameter lam in [0, 1] multiplies every load.
    """

    def __init__(self, K, L, f0, Fd, Md, Ff, Mf, q, M):
        self.L = L
        self.M = M
        Kww = np.abs(np.diag(K)[3:])
        self.Fs = float(np.max(Kww)) / L**2
        S = np.array([1.0, 1.0, 1.0, L, L, L])
        W = self.Fs * np.array([1.0, 1.0, 1.0, L, L, L])
        self.Ct = (S[:, None] * np.linalg.inv(K)) * W[None, :]
        self.f0t = S * f0
        self.Fd = Fd / self.Fs
        self.Md = Md / (self.Fs * L)
        self.Ff = Ff / self.Fs
        self.Mf = Mf / (self.Fs * L)
        self.q = q * L / self.Fs
        self.n_shoot = 0
        self.load_scale = (np.linalg.norm(self.Fd) + np.linalg.norm(self.Md)
                           + np.linalg.norm(self.Ff) + np.linalg.norm(self.Mf)
                           + np.linalg.norm(self.q))
        ls = max(self.load_scale, 1e-300)
        # scale of every unknown / continuity equation: positions and
        # rotation entries ~ 1, internal forces and moments ~ the load
        seg_scale = np.r_[np.ones(12), np.full(6, ls)]
        self.z_scale = np.r_[np.full(6, ls), np.tile(seg_scale, M - 1)]
        self.F_scale = np.r_[np.tile(seg_scale, M - 1), np.full(6, ls)]
        self.nz = 6 + _NS * (M - 1)

    # -- right-hand side for all segments (and sensitivity columns) at once
    def rhs(self, tau, y, lam, sens):
        M = self.M
        h = 1.0 / M
        Y = y.reshape(M, -1)
        R = Y[:, 3:12].reshape(M, 3, 3)
        n, m = Y[:, 12:15], Y[:, 15:18]
        sig = np.concatenate([(n[:, None, :] @ R)[:, 0], (m[:, None, :] @ R)[:, 0]], axis=1)
        f = self.f0t + sig @ self.Ct.T
        fu, fw = f[:, :3], f[:, 3:]
        dP = (R @ fu[:, :, None])[:, :, 0]
        Wf = _hat(fw)
        dR = R @ Wf
        dn = np.broadcast_to(-lam * self.q, (M, 3))
        dm = _cross(n, dP)                              # -p' x n
        core = np.concatenate([dP, dR.reshape(M, 9), dn, dm], axis=1)
        if not sens:
            return h * core.ravel()
        # variational equations: one row per column of d(state)/d(y0, lam)
        Sm = Y[:, _NS:].reshape(M, _NC, _NS)
        sR = Sm[:, :, 3:12].reshape(M, _NC, 3, 3)
        sn, sm = Sm[:, :, 12:15], Sm[:, :, 15:18]
        dsig = np.concatenate([(n[:, None, None, :] @ sR)[:, :, 0] + sn @ R,
                               (m[:, None, None, :] @ sR)[:, :, 0] + sm @ R], axis=2)
        df = dsig @ self.Ct.T
        ddP = (sR @ fu[:, None, :, None])[..., 0] + df[:, :, :3] @ np.swapaxes(R, 1, 2)
        G = (R[:, None] @ _HAT_BASIS).reshape(M, 3, 9)      # rows: R hat(e_l)
        ddR = (sR @ Wf[:, None]).reshape(M, _NC, 9) + df[:, :, 3:] @ G
        ddn = np.zeros((M, _NC, 3))
        ddn[:, -1] = -self.q
        ddm = _cross(n[:, None, :], ddP) + _cross(sn, dP[:, None, :])
        dS = np.concatenate([ddP, ddR, ddn, ddm], axis=2).reshape(M, -1)
        return h * np.concatenate([core, dS], axis=1).ravel()

    def starts(self, z):
        """(M, 18) segment start states from the unknowns."""
        Y0 = np.empty((self.M, _NS))
        Y0[0, :3] = 0.0
        Y0[0, 3:12] = np.eye(3).ravel()
        Y0[0, 12:] = z[:6]
        Y0[1:] = z[6:].reshape(self.M - 1, _NS)
        return Y0

    def reference_z(self):
        """Unknowns of the unloaded rod: H(t_k) = exp(t_k hat6(f0)), no wrench."""
        z = np.zeros(self.nz)
        for k in range(1, self.M):
            H = expm(_hat6(self.f0t * k / self.M))
            z[6 + _NS * (k - 1):6 + _NS * (k - 1) + 12] = np.r_[H[:3, 3], H[:3, :3].ravel()]
        return z

    def integrate(self, z, lam, rtol, atol, sens, dense=False):
        self.n_shoot += 1
        if self.n_shoot > _MAX_SHOOTS:
            raise _BudgetExceeded(f"more than {_MAX_SHOOTS} shooting integrations")
        Y0 = self.starts(z)
        if sens:
            S0 = np.zeros((self.M, _NC, _NS))
            S0[:, np.arange(_NS), np.arange(_NS)] = 1.0
            y0 = np.concatenate([Y0, S0.reshape(self.M, -1)], axis=1).ravel()
        else:
            y0 = Y0.ravel()
        sol = solve_ivp(self.rhs, (0.0, 1.0), y0, method="DOP853", rtol=rtol, atol=atol,
                        args=(lam, sens), dense_output=dense)
        if not sol.success:
            raise ContinuumConvergenceError(f"solve_ivp failed: {sol.message}")
        return sol

    def shoot(self, z, lam, rtol, atol):
        """Residual F (nz,), Jacobian dF/dz (nz, nz) and dF/dlam (nz,)."""
        M, nz = self.M, self.nz
        sol = self.integrate(z, lam, rtol, atol, sens=True)
        Yend = sol.y[:, -1].reshape(M, -1)
        Phi = Yend[:, _NS:].reshape(M, _NC, _NS).transpose(0, 2, 1)  # (M, 18, 19)
        Ye = Yend[:, :_NS]
        F = np.zeros(nz)
        J = np.zeros((nz, nz))
        Fl = np.zeros(nz)

        def cols(k):           # columns of segment k's unknown start state
            return slice(0, 6) if k == 0 else slice(6 + _NS * (k - 1), 6 + _NS * k)

        def dstart(k):         # d(start state of k)/d(its unknowns)
            return Phi[k][:, 12:18] if k == 0 else Phi[k][:, :_NS]

        Y0 = self.starts(z)
        for k in range(M - 1):
            rows = slice(_NS * k, _NS * (k + 1))
            F[rows] = Ye[k] - Y0[k + 1]
            J[rows, cols(k)] = dstart(k)
            J[rows, cols(k + 1)] -= np.eye(_NS)
            Fl[rows] = Phi[k][:, _NS]
        # tip: n(1) = lam (Fd + R Ff), m(1) = lam (Md + R Mf)
        RL = Ye[-1, 3:12].reshape(3, 3)
        Ft = self.Fd + RL @ self.Ff
        Mt = self.Md + RL @ self.Mf
        rows = slice(nz - 6, nz)
        F[rows] = np.r_[Ye[-1, 12:15] - lam * Ft, Ye[-1, 15:18] - lam * Mt]
        Gt = np.zeros((6, _NS))
        Gt[0:3, 12:15] = np.eye(3)
        Gt[3:6, 15:18] = np.eye(3)
        Gt[0:3, 3:12] = -lam * np.kron(np.eye(3), self.Ff)
        Gt[3:6, 3:12] = -lam * np.kron(np.eye(3), self.Mf)
        J[rows, cols(M - 1)] = Gt @ dstart(M - 1)
        Fl[rows] = Gt @ Phi[-1][:, _NS] - np.r_[Ft, Mt]
        return F, J, Fl


def _hat6(x):
    out = np.zeros((4, 4))
    out[:3, :3] = _hat(x[3:])
    out[:3, 3] = x[:3]
    return out


def _newton(prob, z, lam, rtol, atol, tol, max_iter, dz_limit=np.inf, polish=True):
    """Damped Newton on the multiple-shooting equations at load ``lam``.

    Converged when the Newton correction, scaled per unknown (positions /L,
    rotation entries, forces and moments / total load), is <= tol; that last
    correction is applied and the system re-evaluated, so the error is
    O(tol^2) + integration error (with ``polish=False`` the correction is
    applied but J and dF/dlam are those of the previous iterate and F is not
    updated: enough for a continuation step). Also stops at the integration
    noise floor.
    Returns (z, F, J, dF/dlam, iterations); raises ContinuumConvergenceError,
    immediately if the first correction exceeds ``dz_limit`` (scaled): the
    predictor was too far off, take a smaller load step.
    """
    zs, Fs = prob.z_scale, prob.F_scale
    F, J, Fl = prob.shoot(z, lam, rtol, atol)
    for it in range(max_iter):
        try:
            dz = -np.linalg.solve(J, F)
        except np.linalg.LinAlgError as exc:
            raise ContinuumConvergenceError("singular shooting Jacobian") from exc
        if not np.all(np.isfinite(dz)):
            raise ContinuumConvergenceError("non-finite Newton step")
        e = np.max(np.abs(dz) / zs)
        if it == 0 and e > dz_limit:
            raise ContinuumConvergenceError("predictor too far from the equilibrium")
        # converged, or the correction is at the integration noise floor
        if e <= tol or np.all(np.abs(dz) <= 10.0 * rtol * (np.abs(z) + zs)):
            z = z + dz
            if polish:
                F, J, Fl = prob.shoot(z, lam, rtol, atol)
            return z, F, J, Fl, it + 1
        merit = np.linalg.norm(F / Fs)
        step = 1.0
        while True:
            zn = z + step * dz
            try:
                Fn, Jn, Fln = prob.shoot(zn, lam, rtol, atol)
                if np.linalg.norm(Fn / Fs) < (1.0 - 1e-4 * step) * merit:
                    break
            except _BudgetExceeded:
                raise
            except ContinuumConvergenceError:
                pass
            step *= 0.5
            if step < 1.0 / 16:
                raise ContinuumConvergenceError(
                    f"line search failed at lam={lam:.4g} (|F|={merit:.3e})")
        z, F, J, Fl = zn, Fn, Jn, Fln
    raise ContinuumConvergenceError(f"Newton did not converge at lam={lam:.4g}")


def _auto_segments(prob, K):
    """Number of shooting segments from the tension growth exponent.

    Small bending perturbations of a rod under tension T grow like
    exp(s sqrt(T/EI)); with T bounded by the total applied force, M segments
    keep the per-segment growth below ~e^2."""
    Kww = np.abs(np.diag(K)[3:])
    T = (np.linalg.norm(prob.Fd) + np.linalg.norm(prob.Ff) + np.linalg.norm(prob.q))
    rate = np.sqrt(T * np.max(Kww) / np.min(Kww))     # = L sqrt(T / EI_min)
    return int(np.clip(np.ceil(rate / 2.0), 2, 64))


def solve_cosserat_statics(K, length, *, f0=(1, 0, 0, 0, 0, 0), base_pose=np.eye(4),
                           tip_force_world=(0, 0, 0), tip_moment_world=(0, 0, 0),
                           tip_wrench_body=(0,) * 6,
                           distributed_force_world=(0, 0, 0),
                           n_nodes=200, tol=1e-10, load_steps=None,
                           rtol=1e-12, atol=1e-14, n_segments=None) -> ContinuumSolution:
    """Static equilibrium of a uniform Cosserat rod, clamped at the base, loaded at the tip.

    Parameters
    ----------
    K : (6, 6) cross-section stiffness acting on ``f - f0`` (SI: N for the
        force block, N m^2 for the moment block; e.g. diag(EA, G A2, G A3,
        G J, E I2, E I3)). Must be invertible; need not be diagonal.
    length : rod length L [m].
    f0 : (6,) constant reference strain [1, 1/m] (straight: [1,0,0,0,0,0]).
    base_pose : (4, 4) world pose of the clamped base section.
    tip_force_world, tip_moment_world : (3,) dead tip load [N], [N m], fixed
        in world axes, acting on the tip section (moment is a pure couple).
    tip_wrench_body : (6,) follower tip load [force N; moment N m] in the
        (deformed) tip section frame.
    distributed_force_world : (3,) dead force per unit length [N/m] on the
        centre line (``rho A g`` for gravity).
    n_nodes : number of output grid points (uniform in s, including both ends).
    tol : Newton tolerance on the correction of the unknowns, relative
        (positions to L, forces and moments to the total applied load).
    load_steps : None for adaptive load continuation (first tries the full
        load, halves the increment on failure); an int N to start with
        increments of 1/N (still adapted).
    rtol, atol : solve_ivp (DOP853) tolerances on the nondimensional state
        (lengths / L, forces / (max(K_ww)/L^2)) for the final solve.
    n_segments : number of multiple-shooting segments (None: automatic,
        2..64 from the load; 1 = simple shooting).

    Returns
    -------
    ContinuumSolution (see its docstring for frames and signs). ``info``
    holds load steps, Newton iterations, failed (halved) steps, number of
    integrations, segments and the final scaled residual.

    Raises ContinuumConvergenceError if the continuation stalls: it follows
    the load parameter, not arc length, so it cannot pass limit points, and
    at a bifurcation (e.g. an axially compressed straight rod beyond Euler's
    load) it stays on the trivial (unstable) branch.
    """
    K = np.asarray(K, dtype=float)
    if K.shape != (6, 6):
        raise ValueError(f"K must be 6x6, got {K.shape}")
    L = float(length)
    if not L > 0:
        raise ValueError("length must be > 0")
    f0 = np.asarray(f0, dtype=float).reshape(6)
    H0 = np.asarray(base_pose, dtype=float).reshape(4, 4)
    R0, p0 = H0[:3, :3], H0[:3, 3]
    wb = np.asarray(tip_wrench_body, dtype=float).reshape(6)
    # dead loads in the base frame
    Fd = R0.T @ np.asarray(tip_force_world, dtype=float).reshape(3)
    Md = R0.T @ np.asarray(tip_moment_world, dtype=float).reshape(3)
    q = R0.T @ np.asarray(distributed_force_world, dtype=float).reshape(3)
    n_nodes = int(n_nodes)
    if n_nodes < 2:
        raise ValueError("n_nodes must be >= 2")
    prob = _Problem(K, L, f0, Fd, Md, wb[:3], wb[3:], q, 1)
    M = _auto_segments(prob, K) if n_segments is None else int(n_segments)
    if M < 1:
        raise ValueError("n_segments must be >= 1")
    prob = _Problem(K, L, f0, Fd, Md, wb[:3], wb[3:], q, M)

    z = prob.reference_z()
    info = {"load_steps": 0, "newton_iterations": 0, "failed_steps": 0, "segments": M}
    if prob.load_scale > 0:
        # Continuation in the load parameter lam = 0 -> 1 with a loose
        # tolerance (intermediate equilibria need not be exact) and the
        # tangent predictor dz/dlam = -J^-1 dF/dlam, then a tight Newton
        # polish at lam = 1.
        zs = prob.z_scale
        lam = 0.0
        h = 1.0 if load_steps is None else 1.0 / int(load_steps)
        _, J, Fl = prob.shoot(z, 0.0, 1e-8, 1e-11)
        zdot = -np.linalg.solve(J, Fl)
        if load_steps is None:
            # first step: linearised rotation/position change of about 1
            h = 1.0 / max(1.0, float(np.max(np.abs(zdot) / zs)))
        prev = None                  # (lam, z, zdot) of the previous point
        while lam < 1.0:
            h = min(h, 1.0 - lam)
            lam_new = 1.0 if h >= 1.0 - lam else lam + h
            if prev is None:
                guess = z + h * zdot                 # tangent predictor
            else:                                    # cubic Hermite extrapolation
                lp, zp, zdp = prev
                d = lam - lp
                u = (lam_new - lp) / d
                guess = ((2 * u**3 - 3 * u**2 + 1) * zp + (u**3 - 2 * u**2 + u) * d * zdp
                         + (-2 * u**3 + 3 * u**2) * z + (u**3 - u**2) * d * zdot)
            pred = np.max(np.abs(guess - z) / zs)
            try:
                zn, F, Jn, Fln, it = _newton(prob, guess, lam_new, 1e-8, 1e-11, 1e-5, 6,
                                             dz_limit=0.4 * pred + 1e-12, polish=False)
                # Branch following: the corrector must stay close to the
                # predictor, otherwise Newton may have jumped to another
                # equilibrium branch (e.g. a looped, unstable shape).
                corr = np.max(np.abs(zn - guess) / zs)
                dstep = np.max(np.abs(zn - z) / zs)
                if corr > 0.25 * dstep + 1e-12:
                    raise ContinuumConvergenceError("corrector left the predicted branch")
            except _BudgetExceeded:
                raise
            except ContinuumConvergenceError as exc:
                info["failed_steps"] += 1
                h *= 0.5
                if h < 1e-5 or info["failed_steps"] > 40:
                    raise ContinuumConvergenceError(
                        f"load continuation stalled at lam = {lam:.6g}: {exc}") from exc
                continue
            info["newton_iterations"] += it
            info["load_steps"] += 1
            prev = (lam, z, zdot)
            z, lam = zn, lam_new
            zdot = -np.linalg.solve(Jn, Fln)
            # aim at corr / dstep ~ 0.05 (predictor error ~ h^2 or h^4),
            # at most twice the previous step for the extrapolation
            h = min(h * float(np.clip((0.05 * dstep / max(corr, 1e-300)) ** 0.5, 0.5, 2.0)),
                    2.0 * h)
        z, F, J, Fl, it = _newton(prob, z, 1.0, rtol, atol, tol, 20)
        info["newton_iterations"] += it
        info["residual"] = float(np.max(np.abs(F) / prob.F_scale))
    else:
        info["residual"] = 0.0

    # output: integrate the converged segments once more with dense output
    sol = prob.integrate(z, 1.0, rtol, atol, sens=False, dense=True)
    info["integrations"] = prob.n_shoot
    t = np.linspace(0.0, 1.0, n_nodes)
    seg = np.minimum((t * M).astype(int), M - 1)
    Y = np.empty((n_nodes, _NS))
    for k in np.unique(seg):
        idx = seg == k
        Y[idx] = sol.sol(t[idx] * M - k).reshape(M, _NS, -1)[k].T
    P = Y[:, 0:3] * L
    R = Y[:, 3:12].reshape(-1, 3, 3)
    # remove the O(rtol) drift from orthogonality (polar factor)
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    nb = Y[:, 12:15] * prob.Fs
    mb = Y[:, 15:18] * prob.Fs * L
    sigma = np.concatenate([np.einsum("nji,nj->ni", R, nb), np.einsum("nji,nj->ni", R, mb)],
                           axis=1)
    strains = f0 + sigma @ np.linalg.inv(K).T
    poses = np.zeros((n_nodes, 4, 4))
    poses[:, :3, :3] = R0 @ R
    poses[:, :3, 3] = p0 + P @ R0.T
    poses[:, 3, 3] = 1.0
    n_w = nb @ R0.T
    m_w = mb @ R0.T
    base = -np.concatenate([n_w[0], m_w[0]])
    return ContinuumSolution(s=t * L, poses=poses, strains=strains,
                             internal_wrench=sigma, base_wrench_world=base,
                             internal_wrench_world=np.concatenate([n_w, m_w], axis=1),
                             info=info)

# ----------------------------------------------------------------------------
# Elastica cantilever (Bisshopp & Drucker 1945)
# ----------------------------------------------------------------------------

def _elastica_tip_angle(alpha):
    """Tip slope theta0 in (0, pi/2) [rad] solving sqrt(alpha) = K(k) - F(phi1, k).

    With theta the tangent angle below the horizontal, EI theta'' = -P cos theta,
    theta(0) = 0, theta'(L) = 0; the substitution 1 + sin(theta) = 2 k^2 sin^2(phi)
    (2 k^2 = 1 + sin(theta0), sin(phi1) = 1/(sqrt(2) k)) gives
    ds = dphi / (sqrt(P/EI) sqrt(1 - k^2 sin^2 phi)).
    scipy's elliptic integrals take the parameter m = k^2.
    """
    if not alpha > 0:
        raise ValueError("alpha must be > 0")
    sa = np.sqrt(alpha)

    def g(t):
        m = 0.5 * (1.0 + np.sin(t))
        m1 = np.sin(0.25 * np.pi - 0.5 * t) ** 2      # 1 - m without cancellation
        phi1 = np.arcsin(1.0 / np.sqrt(1.0 + np.sin(t)))
        return ellipkm1(m1) - ellipkinc(phi1, m) - sa

    return brentq(g, 0.0, 0.5 * np.pi - 1e-15, xtol=1e-16, rtol=4 * np.finfo(float).eps,
                  maxiter=200)


def elastica_cantilever_tip_angle(alpha):
    """Tip rotation [rad] of the elastica cantilever for alpha = P L^2/(E I) [-]."""
    return float(_elastica_tip_angle(alpha))


def elastica_cantilever_tip(alpha):
    """Tip position of an inextensible, unshearable cantilever under a dead transverse tip load.

    The beam (length L, bending stiffness EI) is clamped at the origin along
    +x; a force P of fixed direction perpendicular to the undeformed axis
    acts at the tip. ``alpha = P L^2 / (E I)`` [-] (valid for any alpha > 0;
    tested on [0.01, 15]).

    Returns ``(x_tip / L, deflection / L)`` [-]: the tip coordinate along the
    undeformed axis and the tip displacement in the load direction.

    Closed form (Bisshopp & Drucker 1945; see :func:`_elastica_tip_angle`):
        x_tip / L      = 2 k cos(phi1) / sqrt(alpha) = sqrt(2 sin(theta0) / alpha)
        deflection / L = 1 - 2 [E(k) - E(phi1, k)] / sqrt(alpha)
    Mattiasson (1981), table: alpha = 1 -> deflection/L = 0.30172,
    1 - x_tip/L = 0.05643; alpha = 10 -> 0.81061, 0.49346.
    """
    t = _elastica_tip_angle(alpha)
    sa = np.sqrt(alpha)
    m = 0.5 * (1.0 + np.sin(t))
    phi1 = np.arcsin(1.0 / np.sqrt(1.0 + np.sin(t)))
    x = np.sqrt(2.0 * np.sin(t) / alpha)
    y = 1.0 - 2.0 * (ellipe(m) - ellipeinc(phi1, m)) / sa
    return float(x), float(y)


# ----------------------------------------------------------------------------
# Planar rods joined by rigid junctions: clamped-clamped beams and parallel
# continuum robots (a boundary-value problem solved by collocation)
# ----------------------------------------------------------------------------

@dataclass
class PlanarRod:
    """A uniform planar Reissner rod in the x-z plane: axial stiffness EA [N],
    shear stiffness GA [N], bending stiffness EI [N m^2] (about y), length L
    [m]. ``start`` and ``end``: ("world", (x, z, theta)) a clamp at that pose,
    or ("junction", j, (ox, oz, otheta)) rigidly attached to junction j at
    that offset in the junction's frame. theta is the rotation about +y
    (R = Ry(theta); the tangent is (cos theta, -sin theta) in (x, z))."""
    EA: float
    GA: float
    EI: float
    L: float
    start: tuple
    end: tuple


@dataclass
class PlanarRodsSolution:
    """Solution of :func:`solve_planar_rods`: ``junctions`` (J, 3) poses
    (x, z, theta); per rod ``s`` (n,) and ``states`` (6, n) = [x, z, theta,
    n_x, n_z, m_y] with (n, m) the world force and moment (about p(s)) the
    distal part exerts on the proximal part; ``wrench_at(k, s)``."""
    junctions: np.ndarray
    rods: list
    sol: object

    def state(self, k, s):
        """[x, z, theta, n_x, n_z, m_y] of rod k at arc lengths s."""
        L = self.rods[k].L
        y = self.sol.sol(np.atleast_1d(np.asarray(s, float)) / L)
        return y[6 * k:6 * k + 6]


def _Ry_xz(th, o):
    c, s = np.cos(th), np.sin(th)
    return np.array([c * o[0] + s * o[1], -s * o[0] + c * o[1]])


def solve_planar_rods(rods, junction_loads, junction_guess, *, tol=1e-10, n_nodes=101, guess=None):
    """Static equilibrium of planar rods joined by massless rigid junctions.

    Each rod's state y = [x, z, theta, n_x, n_z, m_y] obeys, with the body
    strains from the internal force n = (n_x, n_z) and moment m_y
    (axial N = n . t, shear V = n . e3, e3 = (sin, cos)):
    ``p' = (1 + N/EA) t + (V/GA) e3``, ``theta' = m_y/EI``, ``n' = 0`` and
    ``m_y' = -(p' x n)_y`` (no distributed load). Boundary conditions: a
    clamp fixes (x, z, theta); an attachment to junction j ties the end pose
    to the junction's unknown pose; each junction balances its load
    ``junction_loads[j] = (f_x, f_z, m_y)`` (moment about the junction origin)
    against the rods' end wrenches. All rods are mapped to tau = s/L in [0, 1]
    and solved together by ``scipy.integrate.solve_bvp`` (junction poses are
    its unknown parameters). An independent reference for the multibody
    engine's closed chains (test_constrained.py)."""
    from scipy.integrate import solve_bvp
    R = len(rods)
    J = len(junction_loads)
    loads = np.asarray(junction_loads, float).reshape(J, 3)

    def fun(t, y, p):
        out = np.empty_like(y)
        for k, rod in enumerate(rods):
            x, z, th, nx, nz, my = y[6 * k:6 * k + 6]
            c, si = np.cos(th), np.sin(th)
            N = nx * c - nz * si
            V = nx * si + nz * c
            eps, gam = 1 + N / rod.EA, V / rod.GA
            dx = eps * c + gam * si
            dz = -eps * si + gam * c
            out[6 * k:6 * k + 6] = rod.L * np.vstack([dx, dz, my / rod.EI, 0 * t, 0 * t,
                                                     -(dz * nx - dx * nz)])
        return out

    def end_pose(spec, p):
        if spec[0] == "world":
            return np.asarray(spec[1], float)
        j, o = spec[1], np.asarray(spec[2], float)
        pj = p[3 * j:3 * j + 3]
        return np.r_[pj[:2] + _Ry_xz(pj[2], o[:2]), pj[2] + o[2]]

    def bc(ya, yb, p):
        res = []
        bal = loads.copy()
        for k, rod in enumerate(rods):
            a, b = ya[6 * k:6 * k + 6], yb[6 * k:6 * k + 6]
            res += list(a[:3] - end_pose(rod.start, p))
            res += list(b[:3] - end_pose(rod.end, p))
            # the junction at the start receives +(n, m) of s = 0, at the end -(n, m) of s = L
            for spec, y, sign in ((rod.start, a, 1.0), (rod.end, b, -1.0)):
                if spec[0] != "junction":
                    continue
                j = spec[1]
                r = y[:2] - p[3 * j:3 * j + 2]
                f = sign * y[3:5]
                bal[j, :2] += f
                bal[j, 2] += sign * y[5] + (r[1] * f[0] - r[0] * f[1])
        return np.array(res + list(bal.ravel()))

    t = np.linspace(0.0, 1.0, n_nodes)
    if guess is None:
        y0 = np.zeros((6 * R, n_nodes))
        for k, rod in enumerate(rods):
            a = end_pose(rod.start, np.asarray(junction_guess, float).ravel())
            b = end_pose(rod.end, np.asarray(junction_guess, float).ravel())
            for r in range(3):
                y0[6 * k + r] = a[r] + t * (b[r] - a[r])
    else:
        y0 = guess
    sol = solve_bvp(fun, bc, t, y0, p=np.asarray(junction_guess, float).ravel(), tol=tol, max_nodes=200000,
                    bc_tol=1e-12)
    if not sol.success:
        raise ContinuumConvergenceError(f"solve_bvp: {sol.message}")
    return PlanarRodsSolution(sol.p.reshape(J, 3), list(rods), sol)
