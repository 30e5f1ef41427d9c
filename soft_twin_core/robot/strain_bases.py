"""Variable-strain (GVS) segments: a strain basis per segment of a robot file.

A segment with ``strain_basis`` takes, for each of its free strain modes a,
the field ``xi_a(X) = f0_a + sum_j phi_j(X / L) z_(a, j)`` along its length
L, with the basis functions ``phi_j`` of the chosen family; the
coefficients z are the robot's coordinates instead of one strain per
section. The segment's sections (``sections:``) are the field's
integration points: each takes the field's value at its midpoint as its
constant strain (the second-order Magnus (Zanna) step of the interval), so
the engine's O(n) passes run over the sections as before, and the robot's
configuration is linear in its coordinates,

    q = q0 + B z,    B[(section k, mode a), (a, j)] = phi_j(x_k),  x_k the midpoint / L

(:func:`segment_columns`; :attr:`mechanism.Mechanism.coordinates` assembles B
for the whole robot, the identity for coordinates outside any such segment).
Every algorithm then works in z by the chain rule: generalised forces
``B^T tau``, inertia ``B^T M B``, stiffness ``B^T K B``, Jacobians ``J B``.

Families (``type``), on the abscissa x in [0, 1] along the segment:

- ``legendre``: P_j(2 x - 1), j = 0..order (orthogonal: well conditioned);
- ``chebyshev``: T_j(2 x - 1);
- ``monomial``: x^j (simple; ill conditioned beyond order 6 or so);
- ``fem_linear``: hat functions on ``elements`` equal elements (the nodal
  values are the coordinates, a strain continuous and piecewise linear);
- ``fem_cubic``: continuous piecewise cubic Lagrange, 4 equally spaced
  nodes an element.

Robot file (``segments[i]``)::

    strain_basis: {type: legendre, order: 3}
    strain_basis: {type: legendre, order: {bending_y: 3, bending_z: 3, torsion: 1}}   # every free mode
    strain_basis: {type: fem_cubic, elements: 2}
    strain_basis: {type: legendre, order: 3, magnus: 4}    # the fourth-order step (soft_chain)

``magnus: 4`` replaces the midpoint samples by the commutator-free
fourth-order Magnus step between the sections' Gauss points, with the
mass at those points and the field's own elasticity
(:mod:`soft_twin_core.robot.soft_chain`): the error falls as n^-4 instead
of n^-2 in the sections, for the same coordinates.

Order 0 on every mode is one constant strain over the segment (its
sections move together, as one PCS section of the segment's length would).
"""

from dataclasses import dataclass

import numpy as np

from soft_twin_core.errors import ModelError

# the strain modes, in the engine's order (the robot file's names)
STRAIN_NAMES = ("axial", "shear_y", "shear_z", "torsion", "bending_y", "bending_z")
GLOBAL_TYPES = ("legendre", "chebyshev", "monomial")
FEM_TYPES = {"fem_linear": 1, "fem_cubic": 3}
BASIS_TYPES = GLOBAL_TYPES + tuple(FEM_TYPES)
MAX_ORDER = 12          # global bases: beyond it the sections needed and the conditioning are not worth it
MAX_ELEMENTS = 64
MAGNUS_ORDERS = (2, 4)
GAUSS2 = 0.5 / np.sqrt(3.0)      # the 2-point Gauss abscissae: an interval's midpoint -+ this times its length
CF_WEIGHTS = (0.25 + np.sqrt(3.0) / 6, 0.25 - np.sqrt(3.0) / 6)   # the commutator-free method's a1, a2


@dataclass(frozen=True)
class StrainBasis:
    """A segment's basis: family ``kind``, and per free mode (in the order
    of the segment's free modes) its global ``orders`` (global families) or
    the FEM ``elements`` (every free mode alike)."""
    kind: str
    orders: tuple = ()
    elements: int = 0
    magnus: int = 2        # the Magnus step's order: 2 (midpoints) or 4 (soft_chain's commutator-free step)

    def functions(self, mode_index):
        """How many basis functions free mode number ``mode_index`` has."""
        if self.kind in FEM_TYPES:
            return self.elements * FEM_TYPES[self.kind] + 1
        return self.orders[mode_index] + 1

    def values(self, mode_index, x):
        """(functions, len(x)): the basis functions of free mode number
        ``mode_index`` at the abscissae x in [0, 1] along the segment."""
        x = np.asarray(x, dtype=float)
        if self.kind in FEM_TYPES:
            return lagrange_shapes(x, self.elements, FEM_TYPES[self.kind])
        return global_values(self.kind, self.orders[mode_index], x)


@dataclass(frozen=True, eq=False)
class CustomBasis:
    """A basis from a Python callable (the core's API, not the robot
    file): ``function(x)`` gives the values (k, len(x)) of k functions at
    the abscissae x in [0, 1] along the member, the same for every free
    mode (:func:`mechanism.with_strain_basis`). Checked where it is used:
    finite, the shape, and functions the sections' midpoints can tell
    apart."""
    function: object
    kind: str = "custom"

    def values(self, mode_index, x):
        x = np.asarray(x, dtype=float)
        try:
            out = np.asarray(self.function(x), dtype=float)
        except Exception as e:      # noqa: BLE001 (a user's callable: any failure, named)
            raise ModelError(f"strain basis: the callable failed at {len(x)} abscissae: {e!r}") from None
        if out.ndim != 2 or out.shape[1] != len(x) or out.shape[0] < 1 or not np.all(np.isfinite(out)):
            raise ModelError(f"strain basis: the callable must return finite values of shape (k >= 1, {len(x)}) "
                             f"for {len(x)} abscissae, got shape {out.shape}")
        return out

    def functions(self, mode_index):
        return self.values(mode_index, np.array([0.5])).shape[0]


def global_values(kind, order, x):
    """(order + 1, len(x)): the global family ``kind``'s functions 0..order at x in [0, 1]."""
    x = np.asarray(x, dtype=float)
    if kind == "monomial":
        return np.array([x ** j for j in range(order + 1)])
    family = np.polynomial.legendre.Legendre if kind == "legendre" else np.polynomial.chebyshev.Chebyshev
    return np.array([family.basis(j)(2 * x - 1) for j in range(order + 1)])


def lagrange_shapes(x, elements, degree):
    """(elements * degree + 1, len(x)): the continuous piecewise Lagrange
    shape functions of ``degree`` on ``elements`` equal elements of [0, 1]
    (nodes x_j = j / (elements * degree)) at the points x."""
    n = elements * degree
    nodes = np.arange(n + 1) / n
    x = np.asarray(x, dtype=float)
    e = np.minimum((x * elements).astype(int), elements - 1)      # each point's element
    out = np.zeros((n + 1, len(x)))
    for k, (xk, ek) in enumerate(zip(x, e)):
        local = nodes[ek * degree:(ek + 1) * degree + 1]
        for a in range(degree + 1):
            others = np.delete(local, a)
            out[ek * degree + a, k] = np.prod((xk - others) / (local[a] - others))
    return out


def _int_in(v, lo, hi, where):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
        raise ModelError(f"{where}: expected an integer in {lo}..{hi}, got {v!r}")
    return int(v)


def parse_strain_basis(d, free_names, where):
    """The :class:`StrainBasis` of a segment's ``strain_basis`` mapping
    ``d`` (None: none), for its free modes ``free_names``; ModelError
    naming the field (``where``) for an unknown type or key, an order
    outside 0..MAX_ORDER, a per-mode order for a mode that is not free or
    missing for one that is."""
    if d is None:
        return None
    if not isinstance(d, dict):
        raise ModelError(f"{where}: expected a mapping such as {{type: legendre, order: 3}}, got {d!r}")
    kind = d.get("type")
    if kind not in BASIS_TYPES:
        raise ModelError(f"{where}.type: expected one of {list(BASIS_TYPES)}, got {kind!r}")
    if not free_names:
        raise ModelError(f"{where}: the segment frees no strain mode (free_modes), so a basis has nothing to span")
    magnus = d.get("magnus", 2)
    if isinstance(magnus, bool) or magnus not in MAGNUS_ORDERS:
        raise ModelError(f"{where}.magnus: expected 2 (the sections' midpoints) or 4 (the fourth-order step), "
                         f"got {magnus!r}")
    if kind in FEM_TYPES:
        extra = sorted(set(d) - {"type", "elements", "magnus"})
        if extra:
            raise ModelError(f"{where}.{extra[0]}: unknown key for {kind}; it takes 'elements' and 'magnus'")
        return StrainBasis(kind, elements=_int_in(d.get("elements", 1), 1, MAX_ELEMENTS, where + ".elements"),
                           magnus=magnus)
    extra = sorted(set(d) - {"type", "order", "magnus"})
    if extra:
        raise ModelError(f"{where}.{extra[0]}: unknown key for {kind}; it takes 'order' and 'magnus'")
    order = d.get("order")
    if isinstance(order, dict):
        for name in order:
            if name not in free_names:
                raise ModelError(f"{where}.order.{name}: not a free mode of the segment; its free modes: "
                                 f"{list(free_names)}")
        missing = [m for m in free_names if m not in order]
        if missing:
            raise ModelError(f"{where}.order: no order for the free mode(s) {missing} (give every free mode "
                             f"one, 0 for a constant)")
        orders = tuple(_int_in(order[m], 0, MAX_ORDER, f"{where}.order.{m}") for m in free_names)
    else:
        orders = (_int_in(order, 0, MAX_ORDER, where + ".order"),) * len(free_names)
    return StrainBasis(kind, orders, magnus=magnus)


def midpoint_samples(lengths):
    """The second-order step's samples of a segment of sections ``lengths``
    [m]: each section's strain the field at its midpoint, (x (n, 1) in [0,
    1] along the segment, c (n, 1) ones) (:func:`field_rows`)."""
    lengths = np.asarray(lengths, dtype=float)
    x = (np.cumsum(lengths) - 0.5 * lengths) / lengths.sum()
    return x[:, None], np.ones((len(x), 1))


def cf_layout(lengths):
    """The engine sections of a fourth-order segment (:mod:`soft_chain`) of sections
    ``lengths`` [m] (module docstring): (their lengths [m] (4n + 2,), the
    section of the file each belongs to (for its K, D, M), their samples
    (x (4n + 2, 2) in [0, 1] along the segment, c (4n + 2, 2): each
    strain is ``sum_i c_i xi(x_i)``), their mass points (per section
    (abscissae [m], weights [m])))."""
    h = np.asarray(lengths, dtype=float)
    n, L = len(h), float(h.sum())
    start = np.concatenate([[0.0], np.cumsum(h)[:-1]])
    xg = np.ravel(np.column_stack([start + (0.5 - GAUSS2) * h, start + (0.5 + GAUSS2) * h]))
    knots = np.concatenate([[0.0], xg, [L]])
    a1, a2 = CF_WEIGHTS
    out_len, owner, X, C, mass = [], [], [], [], []
    for k, (a, b) in enumerate(zip(knots[:-1], knots[1:])):
        d = b - a
        y = np.array([a + (0.5 - GAUSS2) * d, a + (0.5 + GAUSS2) * d]) / L
        sec = min(int(np.searchsorted(np.cumsum(h), 0.5 * (a + b), side="right")), n - 1)
        for half, c in enumerate(((2 * a1, 2 * a2), (2 * a2, 2 * a1))):
            carries = half == 1 and k < 2 * n          # the Gauss point k at its end, in section k // 2
            out_len.append(0.5 * d)
            owner.append(k // 2 if carries else sec)
            X.append(y)
            C.append(c)
            mass.append((np.array([0.5 * d]), np.array([0.5 * h[k // 2] if carries else 0.0])))
    return np.array(out_len), np.array(owner), (np.array(X), np.array(C)), mass


def field_rows(basis, x, c, n_modes):
    """(n * n_modes, coordinates): each engine section k's strain of free
    mode a as ``sum_i c[k, i] xi_a(x[k, i])`` (x in [0, 1] along the
    segment), rows (section k, mode a) in the engine's order, columns
    (mode a, function j)."""
    x, c = np.asarray(x, dtype=float), np.asarray(c, dtype=float)
    n = x.shape[0]
    blocks = []
    for a in range(n_modes):
        vals = basis.values(a, x.ravel()).reshape(-1, *x.shape)          # (functions, n, samples)
        col = np.zeros((n * n_modes, vals.shape[0]))
        col[a::n_modes, :] = np.einsum("jks,ks->kj", vals, c)
        blocks.append(col)
    return np.hstack(blocks)


def segment_columns(basis, samples, n_modes, where):
    """The segment's block of B: :func:`field_rows` of its engine sections'
    ``samples`` (:func:`midpoint_samples`, or the fourth-order step's,
    :func:`soft_chain.cf_layout`). ModelError (``where``) when the samples
    cannot tell a mode's functions apart (fewer sections than functions:
    the coordinates would not be independent)."""
    block = field_rows(basis, *samples, n_modes)
    for a in range(n_modes):
        cols = [basis.functions(b) for b in range(n_modes)]
        lo = sum(cols[:a])
        sub = block[a::n_modes, lo:lo + cols[a]]
        if np.linalg.matrix_rank(sub) < cols[a]:
            n = len(samples[0])
            raise ModelError(f"{where}: {n} sections cannot carry {cols[a]} basis functions (their samples "
                             f"cannot tell them apart); give the segment more sections than functions, and "
                             f"more for the backbone's accuracy (about 0.14 L / n^2)")
    return block


@dataclass(frozen=True, eq=False)
class SegmentBasis:
    """Where a basis applies: segment ``segment`` of member ``member``, its
    tree joints (sections) ``joints``, its :class:`StrainBasis` ``basis``,
    the joints' ``samples`` of the field (:func:`field_rows`; None: their
    midpoints)."""
    member: str
    segment: str
    joints: tuple
    basis: StrainBasis
    samples: tuple = None


def robot_basis(tree, bases):
    """(B (nv, nz), names): the robot's coordinates z with ``q = q0 + B z``:
    each segment of ``bases`` (:class:`SegmentBasis`) contributes its
    :func:`segment_columns`, every other coordinate an identity column.
    Columns in the order of the tree's joints; names
    ``<member>/<segment>/<mode>/<j>`` for basis coordinates, else the
    joint's name and coordinate index."""
    first = {sb.joints[0]: sb for sb in bases}
    inside = {j for sb in bases for j in sb.joints}
    cols, names = [], []
    for i, joint in enumerate(tree.joints):
        a = int(tree.idx_v[i])
        if i in first:
            sb = first[i]
            modes = joint.section.modes
            rows = np.concatenate([np.arange(tree.idx_v[j], tree.idx_v[j] + len(modes)) for j in sb.joints])
            samples = sb.samples or midpoint_samples([tree.joints[j].section.length for j in sb.joints])
            block = segment_columns(sb.basis, samples, len(modes), f"{sb.member}.{sb.segment}.strain_basis")
            for c in range(block.shape[1]):
                col = np.zeros(tree.nv)
                col[rows] = block[:, c]
                cols.append(col)
            names += [f"{sb.member}/{sb.segment}/{STRAIN_NAMES[m]}/{j}"
                      for k, m in enumerate(modes) for j in range(sb.basis.functions(k))]
        elif i not in inside:
            for c in range(joint.nv):
                col = np.zeros(tree.nv)
                col[a + c] = 1.0
                cols.append(col)
                names.append(f"{joint.name}/{c}")
    B = np.array(cols).T if cols else np.zeros((tree.nv, 0))
    B.setflags(write=False)
    return B, tuple(names)
