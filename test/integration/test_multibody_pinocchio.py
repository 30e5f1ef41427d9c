"""Rigid multibody trees against Pinocchio (an independent implementation).

The same tree is built from one small description (:data:`TREES`) through
our :class:`ModelBuilder` (:func:`build_ours`) and through Pinocchio's
``Model.addJoint`` / ``appendBodyToJoint`` (:func:`build_pin`); then every
quantity of a *backend* (:class:`ReferenceBackend`: the explicit-Jacobian
reference; later the compiled engine, behind the same small adapter) is
compared with Pinocchio's at random states (:func:`check_backend`).

Conventions match Pinocchio's: twists [linear; angular] in body frames
(Pinocchio's LOCAL frame), a joint's placement is its input frame in its
parent's output frame (``jointPlacement``), a body's inertia is about the
joint's output frame, quaternions [x, y, z, w], free-flyer q = [p, quat] and
v = local twist [v; w]. Both configuration and velocity vectors have the same
layout joint by joint, so no reordering is needed.

*Fixed* joints have no Pinocchio joint: their rigid body is appended to the
nearest non-fixed ancestor joint (``appendBodyToJoint`` with the accumulated
placement), and the placement of a joint below a fixed joint is folded: fixed
P followed by J with placement Q is J with placement P @ Q. For every joint
of ours, :class:`PinTree` records the Pinocchio joint id it rides on and the
constant offset ``g_out_ours = oMi[jid] @ offset``.

Reuse (e.g. for the compiled engine)::

    from test_multibody_pinocchio import TREES, build_ours, build_pin, check_backend
    errors = check_backend(MyBackend(), TREES["serial_arm"], seed=0)
"""

from dataclasses import dataclass

import numpy as np
import pytest

pin = pytest.importorskip("pinocchio")

from soft_twin_core import lie
from soft_twin_core.engine import algorithms
from soft_twin_core.engine.joint_kinds import FIXED, FREE, SPHERICAL  # noqa: E402
from soft_twin_core.engine.multibody import ModelBuilder, spatial_inertia  # noqa: E402
from soft_twin_core.reference import joints as jnt  # noqa: E402
from soft_twin_core.reference import multibody as reference  # noqa: E402

TOL = 1e-10          # relative: max |diff| / max(1, max |value|)
FD_TOL = 1e-6        # finite differences of the RNEA
GRAVITY = np.array([0.3, -0.7, -9.81])   # off-axis, so every component matters


# ----------------------------------------------------------------------------
# Tree descriptions
# ----------------------------------------------------------------------------

@dataclass(frozen=True)
class JointDesc:
    """One joint of a test tree. ``parent``: index into the description (-1:
    world); ``placement``: 4x4 input frame in the parent's output frame;
    ``axis``: revolute/prismatic axis; the body: ``mass``, ``com`` (in the
    output frame), ``I_com`` (3x3 about the centre of mass)."""
    name: str
    kind: str
    parent: int
    placement: np.ndarray
    axis: np.ndarray
    mass: float
    com: np.ndarray
    I_com: np.ndarray


def _random_rotation(rng):
    u = rng.normal(size=4)
    return jnt.quat_to_rot(u / np.linalg.norm(u))


def _random_placement(rng, scale=0.4):
    H = np.eye(4)
    H[:3, :3] = _random_rotation(rng)
    H[:3, 3] = rng.uniform(-scale, scale, 3)
    return H


def _random_body(rng):
    """(mass, com, I_com) of a physically consistent body: a rotated box's
    principal moments (positive definite, triangle inequality)."""
    m = rng.uniform(0.5, 3.0)
    a, b, c = rng.uniform(0.05, 0.4, 3)
    d = m / 12.0 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    R = _random_rotation(rng)
    return m, rng.uniform(-0.2, 0.2, 3), R @ np.diag(d) @ R.T


_E = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}


def make_tree(spec, seed):
    """Description list from ``spec``: (name, kind, parent name or None, axis)
    with axis "x"/"y"/"z" (aligned), "u" (random unit vector) or None; random
    placements and bodies from ``seed``."""
    rng = np.random.default_rng(seed)
    names = [s[0] for s in spec]
    out = []
    for name, kind, parent, ax in spec:
        if ax in _E:
            axis = _E[ax]
        elif ax == "u":
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
        else:
            axis = _E["z"]
        m, c, Ic = _random_body(rng)
        out.append(JointDesc(name, kind, -1 if parent is None else names.index(parent),
                             _random_placement(rng), axis, m, c, Ic))
    return tuple(out)


TREES = {
    # (1) 6-joint serial arm: aligned and unaligned revolutes, prismatics;
    #     a fixed tool (with mass) at the end.
    "serial_arm": make_tree([
        ("j1", "revolute", None, "z"),
        ("j2", "revolute", "j1", "u"),
        ("j3", "prismatic", "j2", "x"),
        ("j4", "revolute", "j3", "y"),
        ("j5", "prismatic", "j4", "u"),
        ("j6", "revolute", "j5", "x"),
        ("tool", "fixed", "j6", None),
    ], seed=1),
    # (2) branched: a base revolute with three branches; a fixed joint (with
    #     mass) between two moving joints; a spherical joint on one branch.
    "branched": make_tree([
        ("base", "revolute", None, "z"),
        ("a1", "revolute", "base", "u"),
        ("a2", "prismatic", "a1", "z"),
        ("a3", "revolute", "a2", "x"),
        ("b1", "prismatic", "base", "u"),
        ("b_fix", "fixed", "b1", None),
        ("b2", "revolute", "b_fix", "y"),
        ("c1", "spherical", "base", None),
        ("c2", "revolute", "c1", "u"),
    ], seed=2),
    # (3) floating base carrying a revolute chain with a spherical joint in it,
    #     and a second short branch.
    "floating": make_tree([
        ("base", "free", None, None),
        ("r1", "revolute", "base", "x"),
        ("r2", "revolute", "r1", "u"),
        ("ball", "spherical", "r2", None),
        ("r3", "revolute", "ball", "y"),
        ("p1", "prismatic", "base", "u"),
        ("r4", "revolute", "p1", "z"),
    ], seed=3),
}


# ----------------------------------------------------------------------------
# Builders
# ----------------------------------------------------------------------------

def build_ours(desc, gravity=GRAVITY):
    b = ModelBuilder("pin_test", gravity=gravity)
    for d in desc:
        b.add_joint(d.name, d.kind, parent=d.parent, placement=d.placement, axis=d.axis,
                    inertia=spatial_inertia(d.mass, d.com, d.I_com))
    return b.build()


@dataclass
class PinTree:
    """A Pinocchio model of a description and the map of our joints onto it:
    our joint i's output frame is ``oMi[joint_ids[i]] @ offsets[i]``."""
    model: object
    joint_ids: list
    offsets: list

    def data(self):
        return self.model.createData()


def _pin_joint_model(d):
    for key, e in _E.items():
        if np.array_equal(d.axis, e):
            aligned = key.upper()
            break
    else:
        aligned = None
    if d.kind == "revolute":
        return getattr(pin, f"JointModelR{aligned}")() if aligned else pin.JointModelRevoluteUnaligned(d.axis)
    if d.kind == "prismatic":
        return getattr(pin, f"JointModelP{aligned}")() if aligned else pin.JointModelPrismaticUnaligned(d.axis)
    if d.kind == "spherical":
        return pin.JointModelSpherical()
    if d.kind == "free":
        return pin.JointModelFreeFlyer()
    raise ValueError(d.kind)


def _se3(H):
    return pin.SE3(np.array(H[:3, :3]), np.array(H[:3, 3]))


def build_pin(desc, gravity=GRAVITY):
    model = pin.Model()
    model.gravity = pin.Motion(np.r_[gravity, 0.0, 0.0, 0.0])
    ids, offsets = [], []
    for d in desc:
        pid, poff = (0, np.eye(4)) if d.parent < 0 else (ids[d.parent], offsets[d.parent])
        inertia = pin.Inertia(d.mass, np.array(d.com), np.array(d.I_com))
        if d.kind == "fixed":
            # no Pinocchio joint: the body rides on the parent's joint
            off = poff @ d.placement
            model.appendBodyToJoint(pid, inertia, _se3(off))
            ids.append(pid)
            offsets.append(off)
        else:
            jid = model.addJoint(pid, _pin_joint_model(d), _se3(poff @ d.placement), d.name)
            model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
            ids.append(jid)
            offsets.append(np.eye(4))
    return PinTree(model, ids, offsets)


def sample_state(model, seed):
    """Random (q, v, a) with a seeded rng (q from joints.random_configuration)."""
    rng = np.random.default_rng(seed)
    q = jnt.random_configuration(model, rng)
    return q, rng.normal(size=model.nv), rng.normal(size=model.nv)


# ----------------------------------------------------------------------------
# Backends
# ----------------------------------------------------------------------------

class ReferenceBackend:
    """Adapter: the functions :func:`check_backend` needs, with the
    reference's signatures. Another engine provides the same methods (a
    compiled one would hold its workspace); ``forward_dynamics`` may be left
    to this default (solve with the mass matrix)."""
    name = "reference"

    def placements(self, model, q):
        """(n, 4, 4) world poses of the joints' output frames."""
        return reference.placements(model, q)[1]

    def body_jacobian(self, model, q, i):
        return reference.point_jacobian(model, q, i)

    def body_jacobian_dot(self, model, q, v, i):
        return reference.point_jacobian_dot(model, q, v, i)

    def mass_matrix(self, model, q):
        return reference.mass_matrix(model, q)

    def bias_force(self, model, q, v):
        """C(q, v) v + g(q)."""
        return reference.bias_force(model, q, v) + reference.gravity_force(model, q)

    def gravity_force(self, model, q):
        return reference.gravity_force(model, q)

    def inverse_dynamics(self, model, q, v, a):
        return reference.inverse_dynamics(model, q, v, a)

    def forward_dynamics(self, model, q, v, tau):
        return np.linalg.solve(self.mass_matrix(model, q), tau - self.bias_force(model, q, v))

    def kinetic_energy(self, model, q, v):
        return reference.kinetic_energy(model, q, v)

    def potential_energy(self, model, q):
        return reference.potential_energy(model, q)

    def integrate(self, model, q, v):
        return jnt.integrate(model, q, v)

    def difference(self, model, q1, q2):
        return jnt.difference(model, q1, q2)


def rel_err(ours, theirs):
    ours, theirs = np.asarray(ours, float), np.asarray(theirs, float)
    assert ours.shape == theirs.shape, (ours.shape, theirs.shape)
    return float(np.max(np.abs(ours - theirs), initial=0.0) / max(1.0, np.max(np.abs(theirs), initial=0.0)))


def _canonical_quats(model, q):
    """q with every quaternion's sign chosen w >= 0 (q and -q are one rotation)."""
    q = np.array(q, dtype=float)
    for i, j in enumerate(model.joints):
        a = model.idx_q[i] + (3 if j.kind == FREE else 0)
        if j.kind in (FREE, SPHERICAL) and q[a + 3] < 0:
            q[a:a + 4] *= -1
    return q


def pin_quantities(tree, q, v, a):
    """Pinocchio's side of every comparison (our joint order)."""
    m, d = tree.model, tree.data()
    out = {}
    pin.forwardKinematics(m, d, q, v, a)
    out["placements"] = np.array([d.oMi[jid].homogeneous @ off for jid, off in zip(tree.joint_ids, tree.offsets)])
    Ms = pin.crba(m, d, q)
    out["mass_matrix"] = np.triu(Ms) + np.triu(Ms, 1).T
    out["inverse_dynamics"] = pin.rnea(m, d, q, v, a).copy()
    out["bias_force"] = pin.nonLinearEffects(m, d, q, v).copy()
    out["gravity_force"] = pin.computeGeneralizedGravity(m, d, q).copy()
    out["kinetic_energy"] = pin.computeKineticEnergy(m, d, q, v)
    out["potential_energy"] = pin.computePotentialEnergy(m, d, q)
    out["forward_dynamics"] = pin.aba(m, d, q, v, out["inverse_dynamics"] - 0.5 * out["bias_force"]).copy()
    J, Jd = [], []
    pin.computeJointJacobiansTimeVariation(m, d, q, v)
    dj = m.createData()
    for jid, off in zip(tree.joint_ids, tree.offsets):
        if jid == 0:                           # fixed to the world
            J.append(np.zeros((6, m.nv)))
            Jd.append(np.zeros((6, m.nv)))
            continue
        A = lie.Ad(lie.se3_inv(off))          # constant offset of a fixed joint's frame
        J.append(A @ pin.computeJointJacobian(m, dj, q, jid))
        Jd.append(A @ pin.getJointJacobianTimeVariation(m, d, jid, pin.LOCAL))
    out["body_jacobian"] = np.array(J)
    out["body_jacobian_dot"] = np.array(Jd)
    return out


def check_backend(backend, desc, seed=0, tol=TOL, gravity=GRAVITY):
    """Compare every quantity of ``backend`` on the tree ``desc`` at a random
    state (``seed``) with Pinocchio; assert and return the relative errors."""
    model, tree = build_ours(desc, gravity), build_pin(desc, gravity)
    assert (model.nq, model.nv) == (tree.model.nq, tree.model.nv)
    q, v, a = sample_state(model, seed)
    ref = pin_quantities(tree, q, v, a)
    tau_fd = ref["inverse_dynamics"] - 0.5 * ref["bias_force"]
    ours = {
        "placements": backend.placements(model, q),
        "body_jacobian": np.array([backend.body_jacobian(model, q, i) for i in range(model.n_joints)]),
        "body_jacobian_dot": np.array([backend.body_jacobian_dot(model, q, v, i) for i in range(model.n_joints)]),
        "mass_matrix": backend.mass_matrix(model, q),
        "inverse_dynamics": backend.inverse_dynamics(model, q, v, a),
        "bias_force": backend.bias_force(model, q, v),
        "gravity_force": backend.gravity_force(model, q),
        "kinetic_energy": backend.kinetic_energy(model, q, v),
        "potential_energy": backend.potential_energy(model, q),
        "forward_dynamics": backend.forward_dynamics(model, q, v, tau_fd),
    }
    errors = {k: rel_err(ours[k], ref[k]) for k in ours}
    # potential energy: same zero (world origin, -m g.c); also check a difference
    q2 = sample_state(model, seed + 1000)[0]
    dpe_ours = backend.potential_energy(model, q2) - ours["potential_energy"]
    dpe_pin = pin.computePotentialEnergy(tree.model, tree.model.createData(), q2) - ref["potential_energy"]
    errors["potential_energy_difference"] = rel_err(dpe_ours, dpe_pin)
    bad = {k: e for k, e in errors.items() if not e <= tol}
    assert not bad, f"{backend.name} vs pinocchio, seed {seed}: {bad}"
    return errors


def check_lie_group(backend, desc, seed=0, tol=TOL):
    """integrate / difference against pin.integrate / pin.difference."""
    model, tree = build_ours(desc), build_pin(desc)
    rng = np.random.default_rng(seed)
    q1 = sample_state(model, seed)[0]
    q2 = sample_state(model, seed + 1)[0]
    v = 0.5 * rng.normal(size=model.nv)     # rotation angles < pi: log(exp(v)) = v
    qi_ours = backend.integrate(model, q1, v)
    qi_pin = pin.integrate(tree.model, q1, v)
    errors = {
        "integrate": rel_err(_canonical_quats(model, qi_ours), _canonical_quats(model, qi_pin)),
        "difference": rel_err(backend.difference(model, q1, q2), pin.difference(tree.model, q1, q2)),
        "difference_of_integrate": rel_err(backend.difference(model, q1, qi_ours), v),
    }
    bad = {k: e for k, e in errors.items() if not e <= tol}
    assert not bad, f"{backend.name} vs pinocchio, seed {seed}: {bad}"
    return errors


def check_rnea_derivatives(backend, desc, seed=0, eps=1e-5, tol=FD_TOL):
    """Pinocchio's analytic RNEA derivatives vs central differences of the
    backend's inverse dynamics: w.r.t. v plainly, w.r.t. q on the group
    (q (+) eps e_k with joints.integrate: right-trivialised, the tangent
    displacement in the joint's local frame, Pinocchio's convention)."""
    model, tree = build_ours(desc), build_pin(desc)
    q, v, a = sample_state(model, seed)
    data = tree.model.createData()     # the returned arrays are views into data: keep it alive, copy
    dq_pin, dv_pin, da_pin = (x.copy() for x in pin.computeRNEADerivatives(tree.model, data, q, v, a))
    da_pin = np.triu(da_pin) + np.triu(da_pin, 1).T
    dq, dv = np.zeros((model.nv, model.nv)), np.zeros((model.nv, model.nv))
    for k in range(model.nv):
        e = np.zeros(model.nv)
        e[k] = eps
        dq[:, k] = (backend.inverse_dynamics(model, backend.integrate(model, q, e), v, a)
                    - backend.inverse_dynamics(model, backend.integrate(model, q, -e), v, a)) / (2 * eps)
        dv[:, k] = (backend.inverse_dynamics(model, q, v + e, a)
                    - backend.inverse_dynamics(model, q, v - e, a)) / (2 * eps)
    errors = {"dtau_dq": rel_err(dq, dq_pin), "dtau_dv": rel_err(dv, dv_pin),
              "dtau_da": rel_err(backend.mass_matrix(model, q), da_pin)}
    bad = {k: e for k, e in errors.items() if not e <= tol}
    assert not bad, f"{backend.name} vs pinocchio RNEA derivatives, seed {seed}: {bad}"
    return errors


# ----------------------------------------------------------------------------
# Tests
# ----------------------------------------------------------------------------

class CompiledBackend(ReferenceBackend):
    """The compiled recursive passes (soft_twin_core.engine.algorithms): placements,
    CRBA, RNEA, articulated-body forward dynamics; the rest as the reference."""
    name = "compiled"

    def _ws(self, model):
        from soft_twin_core.engine.workspace import Workspace
        if getattr(self, "_model", None) is not model:
            self._model, self._work = model, Workspace(model)
        return self._work

    def placements(self, model, q):
        return algorithms.forward_kinematics(model, self._ws(model), q)[1].copy()

    def mass_matrix(self, model, q):
        return algorithms.crba(model, self._ws(model), q).copy()

    def bias_force(self, model, q, v):
        return algorithms.rnea(model, self._ws(model), q, v, None).copy()

    def gravity_force(self, model, q):
        return algorithms.rnea(model, self._ws(model), q, None, None).copy()

    def inverse_dynamics(self, model, q, v, a):
        return algorithms.rnea(model, self._ws(model), q, v, a).copy()

    def forward_dynamics(self, model, q, v, tau):
        return algorithms.forward_dynamics(model, self._ws(model), q, v, tau).copy()


BACKENDS = [ReferenceBackend(), CompiledBackend()]


@pytest.mark.parametrize("backend", BACKENDS, ids=lambda b: b.name)
@pytest.mark.parametrize("tree", list(TREES))
@pytest.mark.parametrize("seed", [0, 1])
def test_against_pinocchio(backend, tree, seed):
    check_backend(backend, TREES[tree], seed)


@pytest.mark.parametrize("backend", BACKENDS, ids=lambda b: b.name)
@pytest.mark.parametrize("tree", ["floating", "branched"])
def test_integrate_difference(backend, tree):
    for seed in range(3):
        check_lie_group(backend, TREES[tree], seed)


@pytest.mark.parametrize("backend", BACKENDS, ids=lambda b: b.name)
@pytest.mark.parametrize("tree", list(TREES))
def test_rnea_derivatives_group_convention(backend, tree):
    check_rnea_derivatives(backend, TREES[tree], seed=5)


def test_layouts_match():
    """Same nq/nv per joint (so q and v need no reordering)."""
    for desc in TREES.values():
        ours, tree = build_ours(desc), build_pin(desc)
        for i, j in enumerate(ours.joints):
            if j.kind == FIXED:
                continue
            pj = tree.model.joints[tree.joint_ids[i]]
            assert (pj.idx_q, pj.idx_v, pj.nq, pj.nv) == (ours.idx_q[i], ours.idx_v[i], j.nq, j.nv)


def test_fixed_joint_equals_folded_placement():
    """On our side: fixed P then J (placement Q) == J with placement P @ Q and
    the fixed body's inertia moved to the parent's frame."""
    desc = TREES["branched"]
    k = next(i for i, d in enumerate(desc) if d.kind == "fixed")
    P = desc[k].placement
    b = ModelBuilder("folded", gravity=GRAVITY)
    index = {-1: -1}
    for i, d in enumerate(desc):
        if i == k:
            continue
        parent, placement, I = d.parent, d.placement, spatial_inertia(d.mass, d.com, d.I_com)
        if parent == k:                        # fold the fixed joint's placement
            parent, placement = desc[k].parent, P @ placement
        if i == desc[k].parent:                # carry the fixed body, about this frame
            A = lie.Ad(lie.se3_inv(P))
            I = I + A.T @ spatial_inertia(desc[k].mass, desc[k].com, desc[k].I_com) @ A
        index[i] = b.add_joint(d.name, d.kind, index[parent], placement, d.axis, inertia=I)
    folded, full = b.build(), build_ours(desc)
    q, v, a = sample_state(full, 7)
    assert rel_err(reference.inverse_dynamics(folded, q, v, a), reference.inverse_dynamics(full, q, v, a)) < TOL
    assert rel_err(reference.mass_matrix(folded, q), reference.mass_matrix(full, q)) < TOL
    assert abs(reference.potential_energy(folded, q) - reference.potential_energy(full, q)) < 1e-10


@pytest.mark.parametrize("tree", sorted(TREES))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_analytic_rnea_derivatives_match_pinocchio(tree, seed):
    """The engine's analytic d tau/d q, d tau/d v (soft_twin_core.engine.algorithms.
    rnea_derivatives) equal Pinocchio's computeRNEADerivatives to 1e-10."""
    from soft_twin_core.engine.workspace import Workspace
    desc = TREES[tree]
    model, ptree = build_ours(desc), build_pin(desc)
    q, v, a = sample_state(model, seed)
    data = ptree.model.createData()
    dq_pin, dv_pin, _ = (x.copy() for x in pin.computeRNEADerivatives(ptree.model, data, q, v, a))
    dq, dv = algorithms.rnea_derivatives(model, Workspace(model), q, v, a)
    assert rel_err(dq, dq_pin) < TOL and rel_err(dv, dv_pin) < TOL, (rel_err(dq, dq_pin), rel_err(dv, dv_pin))
