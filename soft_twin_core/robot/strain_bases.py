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


@dataclass(frozen=True)
class StrainBasis:
    """A segment's basis: family ``kind``, and per free mode (in the order
    of the segment's free modes) its global ``orders`` (global families) or
    the FEM ``elements`` (every free mode alike)."""
    kind: str
    orders: tuple = ()
    elements: int = 0

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
    if kind in FEM_TYPES:
        extra = sorted(set(d) - {"type", "elements"})
        if extra:
            raise ModelError(f"{where}.{extra[0]}: unknown key for {kind}; it takes 'elements'")
        return StrainBasis(kind, elements=_int_in(d.get("elements", 1), 1, MAX_ELEMENTS, where + ".elements"))
    extra = sorted(set(d) - {"type", "order"})
    if extra:
        raise ModelError(f"{where}.{extra[0]}: unknown key for {kind}; it takes 'order'")
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
    return StrainBasis(kind, orders)


def segment_columns(basis, lengths, n_modes, where):
    """The segment's block of B: (n_sections * n_modes, coordinates), rows
    (section k, free mode a) in the engine's order, columns (mode a,
    function j); the sections' ``lengths`` [m] give their midpoints.
    ModelError (``where``) when the midpoints cannot tell a mode's functions
    apart (fewer sections than functions: the coordinates would not be
    independent)."""
    lengths = np.asarray(lengths, dtype=float)
    x = (np.cumsum(lengths) - 0.5 * lengths) / lengths.sum()
    n = len(lengths)
    blocks = []
    for a in range(n_modes):
        vals = basis.values(a, x)
        if np.linalg.matrix_rank(vals.T) < len(vals):
            raise ModelError(f"{where}: {n} sections cannot carry {len(vals)} basis functions (their midpoints "
                             f"cannot tell them apart); give the segment more sections than functions, and "
                             f"more for the backbone's accuracy (about 0.14 L / n^2)")
        col = np.zeros((n * n_modes, len(vals)))
        col[a::n_modes, :] = vals.T
        blocks.append(col)
    return np.hstack(blocks)


@dataclass(frozen=True, eq=False)
class SegmentBasis:
    """Where a basis applies: segment ``segment`` of member ``member``, its
    tree joints (sections) ``joints``, its :class:`StrainBasis` ``basis``."""
    member: str
    segment: str
    joints: tuple
    basis: StrainBasis


def segment_bases(member, sections, joints):
    """The :class:`SegmentBasis` of each segment with a basis among a
    member's ``sections`` (:class:`model.Section`, in order) and their tree
    ``joints`` (one each)."""
    out, by_segment = [], {}
    for sec, j in zip(sections, joints):
        if sec.basis is not None:
            by_segment.setdefault(sec.segment, (sec.basis, []))[1].append(int(j))
    for name, (basis, js) in by_segment.items():
        out.append(SegmentBasis(member, name, tuple(js), basis))
    return tuple(out)


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
            block = segment_columns(sb.basis, [tree.joints[j].section.length for j in sb.joints], len(modes),
                                    f"{sb.member}.{sb.segment}.strain_basis")
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
