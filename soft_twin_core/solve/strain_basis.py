"""Variable-strain members by a global strain basis (issue 28, a first slice:
statics of open trees, e.g. a classic rod).

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
sections, its Newton solves are p + 1 per mode. The engine's variable-strain
joint (fewer Gauss points, fourth-order Magnus) is the next step; this gives
the accuracy per generalised coordinate now
(``benchmarks/accuracy_per_dof.py``).
"""

import numpy as np

from soft_twin_core.errors import StaticsError


def legendre_basis(mech, order):
    """B (nv, nz) of Legendre order ``order`` (>= 0) for every soft member of
    ``mech`` without rigid joints (each member's free modes, the sections'
    midpoints normalised to [-1, 1] along it): column (member, mode a, j)."""
    if not (isinstance(order, (int, np.integer)) and order >= 0):
        raise ValueError(f"order: expected an integer >= 0, got {order!r}")
    tree = mech.tree
    soft = set(tree.soft_joints)
    if any(tree.joints[i].nv for i in range(tree.n_joints) if i not in soft):
        raise ValueError("legendre_basis: the robot has rigid joints with coordinates; a strain basis covers "
                         "soft members only")
    cols = []
    for path in tree.paths:
        js = [j for j in path.joints if j in soft]
        if not js:
            continue
        L = np.array([tree.joints[j].section.length for j in js])
        mid = (np.cumsum(L) - 0.5 * L) / L.sum() * 2.0 - 1.0         # midpoints in [-1, 1]
        modes = tree.joints[js[0]].section.modes
        for a in range(len(modes)):
            for j in range(order + 1):
                c = np.zeros(tree.nv)
                vals = np.polynomial.legendre.Legendre.basis(j)(mid)
                for k, jt in enumerate(js):
                    sec = tree.joints[jt].section
                    if len(sec.modes) != len(modes) or np.any(sec.modes != modes):
                        raise ValueError("legendre_basis: a member's sections must share their free modes")
                    c[tree.idx_v[jt] + a] = vals[k]
                cols.append(c)
    return np.array(cols).T if cols else np.zeros((tree.nv, 0))


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
