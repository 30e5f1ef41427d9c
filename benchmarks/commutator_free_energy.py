"""Could the commutator-free Magnus step carry the field's elastic energy in
its sections' own stiffness? (docs/core.md, "Commutator-free form")

An interval of unit length is a path of strains ``c(t) . (xi_1, xi_2)``,
linear in the field at the interval's two Gauss points, c(t) in R^2 (a
section of constant strain where c is constant). With each section's own
stiffness, the elastic energy of a field linear on the interval is exact
(the 2-point Gauss rule's, as a fourth-order method needs) when

    int c = (1/2, 1/2)   and   int c c^T = I / 2,

and the product of the sections' exponentials has the commutator
``[xi_1, xi_2]`` with the coefficient ``S = int int_(s<t) det(c(s), c(t))``,
which Magnus-4 needs to be sqrt(3)/6 = 0.28868.

Two checks:

1. The largest S over smooth paths (c a Legendre series of degree 5 in t,
   SLSQP from 60 starts about the field's own path) under the two
   constraints: it is the field's own linear path's, sqrt(3)/6, and no
   other path found exceeds it.
2. Paths of k = 3 .. 8 constant pieces, palindromic (time-symmetric, so
   that the step's local error keeps only odd powers of d): the least
   residual of the four conditions (first moment, the two second moments,
   S) over 200 starts. It stays away from zero and falls with k, as an
   approximation of the linear path does.

So only the continuous field reaches both, and a robot's commutator-free
form needs the field's stiffness and damping in z, not in its sections.

Run: .venv/bin/python benchmarks/commutator_free_energy.py (about a minute)
"""

import numpy as np
from scipy.optimize import least_squares, minimize

NEEDED = np.sqrt(3.0) / 6
T, W = np.polynomial.legendre.leggauss(40)
T, W = 0.5 * (T + 1), 0.5 * W


def smooth_maximum(degree=5, starts=60, seed=1):
    """(S of the field's own path, the largest S found over paths of the degree)."""
    V = np.polynomial.legendre.legvander(2 * T - 1, degree)

    def path(x):
        return V @ x.reshape(degree + 1, 2)

    def S(x):
        P = x.reshape(degree + 1, 2)
        C = np.stack([np.polynomial.legendre.legval(2 * T - 1, 0.5 * np.polynomial.legendre.legint(P[:, a], lbnd=-1))
                      for a in range(2)], axis=1)                       # int_0^t c
        c = path(x)
        return W @ (C[:, 0] * c[:, 1] - C[:, 1] * c[:, 0])
    cons = [{"type": "eq", "fun": lambda x: W @ path(x) - 0.5},
            {"type": "eq", "fun": lambda x: (lambda c: ((c.T * W) @ c - 0.5 * np.eye(2)).ravel()[[0, 1, 3]])(path(x))}]
    g1, g2 = 0.5 - np.sqrt(3.0) / 6, 0.5 + np.sqrt(3.0) / 6
    own = np.zeros((degree + 1, 2))                  # Lagrange at the Gauss points, in u = 2 t - 1
    own[:2, 0] = np.array([0.5 - g2, 0.5]) / (g1 - g2)
    own[:2, 1] = np.array([0.5 - g1, 0.5]) / (g2 - g1)
    best, rng = S(own.ravel()), np.random.default_rng(seed)
    for _ in range(starts):
        r = minimize(lambda x: -S(x), own.ravel() + 0.3 * rng.standard_normal(own.size), constraints=cons,
                     method="SLSQP", options=dict(maxiter=1000, ftol=1e-14))
        if r.success and max(np.abs(c["fun"](r.x)).max() for c in cons) < 1e-9:
            best = max(best, -r.fun)
    return S(own.ravel()), best


def piecewise_residual(m, odd, starts=200, seed=0):
    """The least residual of the conditions for a palindromic path of 2 m
    (+ 1 if ``odd``) constant pieces."""
    def pieces(x):
        ell, cs = list(np.abs(x[:m])), [x[m + 2 * j:m + 2 * j + 2] for j in range(m)]
        mid = ([abs(x[3 * m])], [np.array([x[3 * m + 1]] * 2)]) if odd else ([], [])
        ell = np.array(ell + mid[0] + ell[::-1])
        return ell / ell.sum(), np.array(cs + mid[1] + [c[::-1] for c in cs[::-1]])

    def residual(x):
        ell, c = pieces(x)
        S = sum(ell[i] * ell[j] * (c[i, 0] * c[j, 1] - c[i, 1] * c[j, 0])
                for i in range(len(ell)) for j in range(i + 1, len(ell)))
        M = (c.T * ell) @ c
        return [ell @ c[:, 0] - 0.5, M[0, 0] - 0.5, M[0, 1], S - NEEDED]
    rng, best = np.random.default_rng(seed), np.inf
    for _ in range(starts):
        x0 = 2 * rng.standard_normal(3 * m + (2 if odd else 0))
        x0[:m] = rng.uniform(0.05, 1.0, m)
        if odd:
            x0[3 * m] = rng.uniform(0.05, 1.0)
        r = least_squares(residual, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        best = min(best, np.abs(residual(r.x)).max())
    return best


def main():
    own, best = smooth_maximum()
    print(f"needed S = {NEEDED:.10f}; the field's own path {own:.10f}; the largest over degree-5 paths {best:.10f}")
    for m, odd in ((1, True), (2, False), (2, True), (3, False), (3, True), (4, False)):
        print(f"{2 * m + odd} constant pieces: least residual {piecewise_residual(m, odd):.2e}", flush=True)


if __name__ == "__main__":
    main()
