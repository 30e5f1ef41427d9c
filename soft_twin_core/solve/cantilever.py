"""The seeds' part C closed form: the deformation field of a uniform
cantilever under a tip wrench (Grazioso, Di Gironimo and Siciliano,
"Analytic solutions for the static equilibrium configurations of externally
loaded cantilever soft robotic arms", RoboSoft 2018).

Derivation (the slides' notation: strain f = [f_u; f_w], its reference f0,
internal wrench sigma = [force; moment] in the cross-section's frame,
``sigma = K (f - f0)``; here ``f`` names the deformation ``f - f0``).
Without distributed loads the body-frame equilibrium is
``sigma' = ad(f)^T sigma`` (the slides' ``sigma' - f^T sigma = g_ext``;
``n' = -kappa x n``, ``m' = -kappa x m - gamma x n``). Linearised about the
reference strain it is ``sigma' = ad(f0)^T sigma``, with constant
coefficients for a uniform member, so

    sigma(a) = F(a) sigma(0),   F(a) = expm(a ad(f0)^T) = Ad(exp_se3(a f0))^T
             = [[L^T, 0], [-hat(T_so3(a f_w0) a f_u0) L^T, L^T]],
    L(a) = exp_so3(a f_w0)

(:func:`wrench_transport`). The slide prints the lower-left block without
its minus sign; the test checks F against ``scipy.linalg.expm``. The tip
condition ``sigma(L) = g_ext(L)`` gives the slide's field

    f(a) = K^-1 F(a) F(L)^-1 g_ext(L)      (:func:`closed_form_strain`)

``F(a) F(L)^-1 = Ad(exp_se3((a - L) f0))^T``: the tip wrench carried back
along the *reference* shape, so a moment is exact while the arm's own
deflection is ignored. The tip wrench is in the tip's reference frame
(for a straight arm on the base's x axis, the base frame). The backbone
integrates ``H' = H hat6(f0 + f(a))`` (:func:`backbone_poses`): exactly
(one exponential) where f is constant, else by the 4th-order Magnus
expansion on Gauss points (Zanna's collocation; Iserles, Munthe-Kaas,
Norsett and Zanna, Acta Numerica 2000).

Exactness: for a pure moment ``tau a`` about a principal axis of K (or any
axis if K's angular block is isotropic about it) the field is constant and
solves the nonlinear equilibrium too (``kappa x K kappa = 0``): it matches
the engine's statics to round-off. For a tip force the error grows with
the load; docs/core.md gives the range where it is a usable predictor
(benchmarks/closed_form_error.py draws it).
"""

import numpy as np

from soft_twin_core.errors import ModelError
from soft_twin_core.lie import ad, exp_se3, exp_so3, hat, T_so3

__all__ = ["wrench_transport", "closed_form_strain", "backbone_poses", "member_closed_form", "ClosedForm"]

_GAUSS = 0.5 * np.array([1 - 1 / np.sqrt(3), 1 + 1 / np.sqrt(3)])     # two-point Gauss nodes on [0, 1]


def wrench_transport(a, f0):
    """The slides' F(a) = Ad(exp_se3(a f0))^T (6x6 for each arc length in
    ``a``, shape (..., 6, 6)): the solution map of ``sigma' = ad(f0)^T sigma``."""
    a = np.asarray(a, float)[..., None]
    f0 = np.asarray(f0, float)
    Lt = np.swapaxes(exp_so3(a * f0[3:]), -1, -2)
    arm = np.einsum("...ij,...j->...i", T_so3(a * f0[3:]), a * f0[:3])
    out = np.zeros(a.shape[:-1] + (6, 6))
    out[..., :3, :3] = Lt
    out[..., 3:, 3:] = Lt
    out[..., 3:, :3] = -hat(arm) @ Lt
    return out


def closed_form_strain(s, K, f0, length, tip_wrench, free=None):
    """The deformation f(s) - f0 (shape (len(s), 6)) of a uniform
    cantilever of stiffness K (6x6 per unit length: N, N m^2), reference
    strain f0 and length [m] under ``tip_wrench`` [N, N m] in its tip's
    reference frame: ``K^-1 F(s) F(L)^-1 g``. ``free``: a mask of the free
    strain modes (default all six); locked modes stay at f0 (their part of
    the wrench is a reaction)."""
    s = np.atleast_1d(np.asarray(s, float))
    # F(s) F(L)^-1 = F(s - L): F is a one-parameter group (expm of a fixed matrix)
    sigma = np.einsum("nij,j->ni", wrench_transport(s - length, f0), np.asarray(tip_wrench, float))
    free = np.ones(6, bool) if free is None else np.asarray(free, bool)
    out = np.zeros((len(s), 6))
    Kf = np.asarray(K, float)[np.ix_(free, free)]
    out[:, free] = np.linalg.solve(Kf, sigma[:, free].T).T
    return out


def backbone_poses(strain, length, points=41, steps=None):
    """Poses (points, 4, 4) at ``points`` equally spaced arc lengths from 0
    to ``length`` of a backbone starting at the identity with strain
    ``strain(s)`` (a callable: (n,) arc lengths -> (n, 6) full strains),
    ``H' = H hat6(strain)``: 4th-order Magnus (two Gauss points, one
    commutator) on at least ``steps`` equal intervals (a whole number
    between outputs; default 32: about 1e-9 L for a tip force bending the
    arm by a third of its length)."""
    n = (points - 1) * max(1, int(np.ceil((32 if steps is None else steps) / (points - 1))))
    h = length / n
    starts = np.arange(n) * h
    xi = strain((starts[:, None] + h * _GAUSS).ravel()).reshape(n, 2, 6)
    omega = 0.5 * h * (xi[:, 0] + xi[:, 1]) + (np.sqrt(3) / 12) * h * h * np.einsum(
        "nij,nj->ni", ad(xi[:, 0]), xi[:, 1])
    steps_exp = exp_se3(omega)
    H = np.empty((n + 1, 4, 4))
    H[0] = np.eye(4)
    for k in range(n):
        H[k + 1] = H[k] @ steps_exp[k]
    return H[::n // (points - 1)]


class ClosedForm:
    """The closed form on one member: ``s`` [m], ``strain`` (full, f0 + f),
    ``poses`` in the member's base frame, ``tip`` (4x4)."""

    def __init__(self, s, strain, poses):
        self.s, self.strain, self.poses = s, strain, poses

    @property
    def tip(self):
        return self.poses[-1]


def _uniform_section(mech, member):
    mem = next((m for m in mech.members if m.name == member), None) if member else mech.members[0]
    if mem is None:
        raise ModelError(f"member {member!r}: no such soft member (have {[m.name for m in mech.members]})")
    secs = [mech.tree.joints[j].section for j in mem.joints]
    first = secs[0]
    for sec in secs[1:]:
        for name in ("K", "f0", "free"):
            if not np.array_equal(getattr(sec, name), getattr(first, name)):
                raise ModelError(f"member {mem.name!r}: the closed form needs a uniform member; its sections' "
                                 f"{name} differ")
    return first, sum(sec.length for sec in secs)


def member_closed_form(mech, tip_wrench, member=None, points=41):
    """The part C closed form for a robot's uniform soft ``member`` (default
    the first) under ``tip_wrench`` [fx, fy, fz, mx, my, mz] (N, N m) in its
    tip's reference frame; poses in the member's base frame."""
    g = np.asarray(tip_wrench, float)
    if g.shape != (6,) or not np.all(np.isfinite(g)):
        raise ValueError("tip_wrench: expected 6 finite values [fx, fy, fz, mx, my, mz] (N, N m)")
    sec, length = _uniform_section(mech, member)

    def strain(s):
        return sec.f0 + closed_form_strain(s, sec.K, sec.f0, length, g, sec.free)
    s = np.linspace(0.0, length, points)
    return ClosedForm(s, strain(s), backbone_poses(strain, length, points))
