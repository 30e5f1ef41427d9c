"""Strain bases for accuracy studies: statics and natural frequencies of
open trees in the coordinates of a basis built here (Legendre, FEM-like);
the fourth-order Magnus field is :mod:`soft_twin_core.solve.magnus4`. A robot
file's ``strain_basis`` (:mod:`soft_twin_core.robot.strain_bases`) puts a segment
on a basis for every solver; these functions are the studies' and the
tests' independent path.

A member's strain field is ``xi(X) = xi_ref(X) + sum_j P_j(2 X / L - 1) z_j``
for each free strain mode, with P_j the Legendre polynomials up to order p:
the p + 1 coefficients z of each mode are the generalised coordinates,
instead of one strain per section. On the engine's PCS discretisation of the
member into n sections (each section's constant strain is the field at its
midpoint: the second-order Magnus step of each interval), the configuration
is linear in z,

    q = q_ref + B z,   B[(section k, mode a), (mode a, j)] = P_j(2 X_k / L - 1),

and the equilibrium R(q) = 0 is solved in z by the principle of virtual work
restricted to the basis (Galerkin): ``B^T R(q_ref + B z) = 0``, tangent
``B^T K_t B`` (:class:`equilibrium.Problem`'s analytic residual and tangent).
Its error is the basis's (spectral for a smooth load) plus the backbone's
midpoint rule (about 0.14 L / n^2: keep n fine); its passes run over the n
sections, its Newton solves are p + 1 per mode
(``benchmarks/accuracy_per_dof.py``).
"""

import numpy as np
from scipy.linalg import eigh

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError
from soft_twin_core.robot.strain_bases import global_values, lagrange_shapes
from soft_twin_core.solve.constrained import dense_stiffness_damping


def _legendre(order, x):
    """(order + 1, len(x)): the Legendre polynomials P_0 .. P_order at the
    abscissae x in [0, 1] of a member (2 x - 1 in [-1, 1]); ValueError
    naming ``order`` unless it is an integer >= 0."""
    if not (isinstance(order, (int, np.integer)) and order >= 0):
        raise ValueError(f"order: expected an integer >= 0, got {order!r}")
    return global_values("legendre", order, np.asarray(x, float))


def _soft_members(mech, what):
    """(member path, its soft joints, their lengths [m]) of every member
    with soft sections; ValueError (``what``) when the robot has rigid
    joints with coordinates (a strain basis covers soft members only)."""
    tree = mech.tree
    soft = set(tree.soft_joints)
    if any(tree.joints[i].nv for i in range(tree.n_joints) if i not in soft):
        raise ValueError(f"{what}: the robot has rigid joints with coordinates; a strain basis covers "
                         f"soft members only")
    for path in tree.paths:
        js = [j for j in path.joints if j in soft]
        if js:
            yield path, js, np.array([tree.joints[j].section.length for j in js])


def legendre_basis(mech, order):
    """B (nv, nz) of Legendre order ``order`` (>= 0) for every soft member of
    ``mech`` without rigid joints (each member's free modes, the sections'
    midpoints normalised to [-1, 1] along it): column (member, mode a, j)."""
    _legendre(order, ())                       # the order checked before any work
    return _member_basis(mech, lambda x: _legendre(order, x), "legendre_basis")


FEM_DEGREES = (1, 3)


def fem_basis(mech, elements, degree):
    """B (nv, nz) of FEM-like local shape functions (the variable-strain
    "FEM-like linear and cubic" bases): each member cut into ``elements``
    equal elements, the strain of each free mode continuous and a
    polynomial of ``degree`` (1: linear, hat functions, elements + 1 nodal
    values; 3: cubic Lagrange, 4 equally spaced nodes an element, 3
    elements + 1 values) inside each; column (member, mode a, node j),
    evaluated at the sections' midpoints. The nodal values are the
    coordinates: a load with a kink (a point load inside the span) is
    followed where the elements are, unlike a global basis."""
    if not (isinstance(elements, (int, np.integer)) and elements >= 1):
        raise ValueError(f"elements: expected an integer >= 1, got {elements!r}")
    if degree not in FEM_DEGREES:
        raise ValueError(f"degree: expected one of {FEM_DEGREES} (linear, cubic), got {degree!r}")
    return _member_basis(mech, lambda x: lagrange_shapes(x, elements, degree), "fem_basis")


def _member_basis(mech, functions, what):
    """B (nv, nz): ``functions(x)`` ((nf, len(x)) values at the abscissae x
    in [0, 1] of a member's sections' midpoints) for each free mode of each
    soft member (a tree without rigid joints with coordinates)."""
    tree = mech.tree
    cols = []
    for path, js, L in _soft_members(mech, what):
        vals = functions((np.cumsum(L) - 0.5 * L) / L.sum())
        if np.linalg.matrix_rank(vals) < len(vals):
            raise ValueError(f"{what}: member {path.name!r} has {len(js)} sections for the basis's {len(vals)} "
                             f"functions, which its midpoints cannot tell apart (coordinates not independent: a "
                             f"singular Newton matrix); give it more sections than functions, and many more for "
                             f"the backbone's accuracy (about 0.14 L / n^2)")
        modes = tree.joints[js[0]].section.modes
        for jt in js:
            sec = tree.joints[jt].section
            if len(sec.modes) != len(modes) or np.any(sec.modes != modes):
                raise ValueError(f"{what}: a member's sections must share their free modes")
        for a in range(len(modes)):
            for f in vals:
                c = np.zeros(tree.nv)
                for k, jt in enumerate(js):
                    c[tree.idx_v[jt] + a] = f[k]
                cols.append(c)
    return np.array(cols).T if cols else np.zeros((tree.nv, 0))


def modal_frequencies(mech, B, q_ref=None, count=None):
    """The natural frequencies [Hz] of small vibrations about ``q_ref``
    (default the reference configuration: with no loads, an equilibrium),
    in the coordinates z of ``q = q_ref + B z``: the generalised
    eigenvalues of the elastic stiffness and the mass matrix projected on
    the basis, ``B^T K B x = w^2 B^T M(q_ref) B x`` (the static tangent of
    the elastic forces, no load stiffness; CRBA's M). ``count``: the
    lowest ones (default all)."""
    tree = mech.tree
    q = tree.q0.copy() if q_ref is None else tree.check_q(np.asarray(q_ref, dtype=float), "q_ref")
    B = np.asarray(B, dtype=float)
    if B.ndim != 2 or B.shape[0] != tree.nv or B.shape[1] < 1 or not np.all(np.isfinite(B)):
        raise ValueError(f"B: expected a finite basis of shape ({tree.nv}, k >= 1) (a column per coordinate, a row "
                         f"per velocity coordinate of the robot), got shape {B.shape}")
    K, _ = dense_stiffness_damping(tree)
    M = alg.crba(tree, Workspace(tree), q).copy()
    w2 = eigh(B.T @ K @ B, B.T @ M @ B, eigvals_only=True)
    f = np.sqrt(np.maximum(w2, 0.0)) / (2 * np.pi)
    return f if count is None else f[:count]


def solve_reduced(pb, B, q_ref, z0=None, *, tol=1e-10, max_iterations=50, load_steps=1):
    """Equilibrium of :class:`equilibrium.Problem` ``pb`` in the coordinates z
    of ``q = q_ref + B z`` (module docstring): Newton on ``B^T R = 0`` with
    ``B^T K_t B``, the inputs raised in ``load_steps`` equal steps, each
    converged to ``|B^T R| <= tol (1 + |B^T R(q_ref)|)``. Returns (q, z,
    total iterations); StaticsError when a step does not converge."""
    B = np.asarray(B, dtype=float)
    q_ref = np.asarray(q_ref, dtype=float)
    z = np.zeros(B.shape[1]) if z0 is None else np.array(z0, dtype=float)
    total = 0
    for step in range(1, load_steps + 1):
        p = pb.scaled(step / load_steps) if load_steps > 1 else pb
        scale = 1.0 + np.abs(B.T @ p.residual(q_ref)).max()
        for it in range(max_iterations):
            q = q_ref + B @ z
            r = B.T @ p.residual(q)
            if np.abs(r).max() <= tol * scale:
                break
            dz = np.linalg.solve(B.T @ p.tangent(q) @ B, -r)
            t, n0 = 1.0, np.linalg.norm(r)
            while t > 1e-4 and np.linalg.norm(B.T @ p.residual(q_ref + B @ (z + t * dz))) > (1 - 1e-4 * t) * n0:
                t *= 0.5                                  # backtracking on |B^T R|
            z = z + t * dz
            total += 1
        else:
            raise StaticsError(f"reduced statics: no convergence in {max_iterations} iterations at load step "
                               f"{step}/{load_steps} (|B^T R| = {np.abs(r).max():.3g})")
    return q_ref + B @ z, z, total
