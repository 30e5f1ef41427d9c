"""How a member's segments become the engine's soft sections: the one place
for it (the classic schema's backbone and every member of the tree schema).

- **PCS segments**, and variable-strain segments of the second-order step
  (``strain_basis`` without ``magnus``, or ``magnus: 2``): one engine
  section per section of the file, with its own mass (Gauss points on its
  arc) and elasticity; a basis samples its field at the sections'
  midpoints (:func:`strain_bases.segment_columns`).
- **Fourth-order segments** (``strain_basis: {..., magnus: 4}``): the
  commutator-free fourth-order Magnus step of the field (Blanes and Moan,
  Applied Numerical Mathematics 56, 2006). The field is sampled at the
  segment's Gauss points, two in each of its n sections,
  ``X_g = X_k + h_k (1/2 -+ sqrt(3)/6)``; between consecutive points (the
  base, the Gauss points, the end: 2n + 1 intervals of length d) two
  engine sections of length d/2 whose strains are linear in the field at
  the interval's own Gauss points Y_1 < Y_2,

      2 (a1 xi(Y_1) + a2 xi(Y_2))  then  2 (a2 xi(Y_1) + a1 xi(Y_2)),   a1, a2 = 1/4 +- sqrt(3)/6

  (:func:`strain_bases.cf_layout`), so the pose at every knot is fourth order in the
  sections and ``q = q0 + B z`` keeps a constant B. The mass sits at the
  Gauss points (the second half of each interval but the last carries
  ``h_k / 2`` of its section's inertia density at its end: 2-point Gauss
  quadrature of the inertia, gravity and distributed loads at points whose
  poses are fourth order). The elasticity is the field's own, ``K_z = int
  Phi^T K Phi dX`` (and ``D_z``), integrated exactly
  (:func:`field_energy`), an :class:`multibody.ElasticField` over the
  segment's engine sections (their own blocks zero): two constant-strain
  sections an interval cannot carry that energy and the fourth order both
  (``benchmarks/commutator_free_energy.py``). Checked against the study's
  field (:func:`solve.magnus4.commutator_free_field`) and for fourth-order
  convergence in ``test_magnus4_robot.py``.

Each interval's two sections are an engine *field pair*
(:class:`multibody.FieldPair`, with the map from their strains to the field
at the interval's Gauss points), so tendons and chambers read the field
there (:mod:`soft_twin_core.engine.forces`): fourth order too. Frames and
contact points read the engine sections as they are: exact at the knots
(the tip, the Gauss points), second order inside an interval.
"""

import numpy as np

from soft_twin_core.engine.multibody import ModelBuilder, SoftSection
from soft_twin_core.robot.strain_bases import CF_WEIGHTS, SegmentBasis, cf_layout, field_rows, midpoint_samples


def field_energy(basis, lengths, K, D, modes):
    """(K_z, D_z) (nz, nz): ``int Phi^T K Phi dX`` and the same of D over
    the segment, exact for polynomial bases: Gauss-Legendre on every piece
    between the sections' ends and the FEM elements' (K, D (n, 6, 6): per
    section of the file, constant on it; ``modes``: the free modes)."""
    h = np.asarray(lengths, dtype=float)
    L = float(h.sum())
    ends = np.concatenate([[0.0], np.cumsum(h)]) / L
    elements = getattr(basis, "elements", 0)
    cuts = np.unique(np.round(np.concatenate([ends, np.arange(elements + 1) / max(elements, 1)]), 14))
    degree = max(getattr(basis, "orders", ()) or (3,)) if elements == 0 else 3
    x, w = np.polynomial.legendre.leggauss(degree + 1)
    nz = field_rows(basis, np.array([[0.5]]), np.ones((1, 1)), len(modes)).shape[1]
    Kz, Dz = np.zeros((nz, nz)), np.zeros((nz, nz))
    sel = np.ix_(modes, modes)
    for a, b in zip(cuts[:-1], cuts[1:]):
        k = min(int(np.searchsorted(ends, 0.5 * (a + b), side="right")) - 1, len(h) - 1)
        xs = a + 0.5 * (b - a) * (x + 1)
        Phi = field_rows(basis, xs[:, None], np.ones((len(xs), 1)), len(modes)).reshape(len(xs), len(modes), nz)
        for P, wi in zip(Phi, 0.5 * (b - a) * L * w):
            Kz += wi * P.T @ K[k][sel] @ P
            Dz += wi * P.T @ D[k][sel] @ P
    return 0.5 * (Kz + Kz.T), 0.5 * (Dz + Dz.T)


def _segments(sections):
    """Consecutive runs of ``sections`` (:class:`model.Section`) by segment: (name, first, end)."""
    out, start = [], 0
    for k in range(1, len(sections) + 1):
        if k == len(sections) or sections[k].segment != sections[start].segment:
            out.append((sections[start].segment, start, k))
            start = k
    return out


def add_member(b, name, robot, kmap, npt, parent, placement):
    """Adds the soft chain of ``robot`` (:class:`model.RobotModel`: its
    sections and segments) to the builder ``b`` after joint ``parent`` at
    ``placement`` (module docstring). Returns (its joints, the section of
    the file each stands for, its :class:`strain_bases.SegmentBasis` es)."""
    secs = robot.sections
    js, owners, bases = [], [], []
    for seg, first, end in _segments(secs):
        group = secs[first:end]
        basis = group[0].basis
        lengths = [s.length for s in group]
        if basis is not None and getattr(basis, "magnus", 2) == 4:      # (the exponential map: model_from_dict)
            lens, own, samples, mass = cf_layout(lengths)
            parts = [SoftSection(d, group[o].K, group[o].D, np.asarray(group[o].M, float),
                                 np.asarray(group[o].f0, float), np.asarray(group[o].free, bool), kmap, npt, mq)
                     for d, o, mq in zip(lens, own, mass)]
            own = first + own
        else:
            parts = [SoftSection(s.length, s.K, s.D, np.asarray(s.M, float), np.asarray(s.f0, float),
                                 np.asarray(s.free, bool), kmap, npt) for s in group]
            own = np.arange(first, end)
            samples = midpoint_samples(lengths) if basis is not None else None
        seg_js = []
        for k, (sec, o) in enumerate(zip(parts, own)):
            pl = placement if not js else (None if k > 0 else secs[first - 1].offset_after)
            parent = b.add_joint(f"{name}_{len(js)}", "soft", parent, pl, section=sec)
            js.append(parent)
            seg_js.append(parent)
        owners += list(own)
        if basis is None:
            continue
        sb = SegmentBasis(name, seg, tuple(seg_js), basis, samples)
        bases.append(sb)
        if getattr(basis, "magnus", 2) == 4:
            a1, a2 = CF_WEIGHTS
            field = np.linalg.inv([[2 * a1, 2 * a2], [2 * a2, 2 * a1]])     # the halves' strains -> the field
            for j1, j2 in zip(seg_js[0::2], seg_js[1::2]):
                b.add_field_pair(j1, j2, field)
            modes = parts[0].modes
            B = field_rows(basis, *samples, len(modes))
            Kz, Dz = field_energy(basis, lengths, [np.asarray(s.K, float) for s in group],
                                  [np.asarray(s.D, float) for s in group], modes)
            b.add_elastic_field(seg_js, np.linalg.pinv(B), Kz, Dz)
    return js, np.array(owners, dtype=np.int64), tuple(bases)


def robot_tree(robot):
    """(tree, owners, bases): the engine tree of a classic robot
    description (one chain of segments: the base pose as the first joint's
    placement, one path "backbone" over the chain, the actuators on it, a
    frame "tip" at its end), with :func:`add_member`'s owners and bases
    (member "backbone")."""
    b = ModelBuilder(robot.name, robot.gravity)
    js, owners, bases = add_member(b, "section", robot, robot.kinematic_map, robot.quadrature_points, -1,
                                   robot.base_pose)
    b.add_path("backbone", js)
    b.add_frame("tip", js[-1], np.eye(4), x=b.joints[js[-1]].section.length)
    b.actuators = tuple(robot.actuators)
    bases = tuple(SegmentBasis("backbone", sb.segment, sb.joints, sb.basis, sb.samples) for sb in bases)
    return b.build(), owners, bases
