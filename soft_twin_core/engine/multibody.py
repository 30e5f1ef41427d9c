"""The multibody model: a kinematic tree of rigid and soft joints (immutable).

A robot is a tree of *joints* in topological order (a parent always comes
before its children). Joint ``i`` connects the *output frame* of its parent
(the world frame for ``parent == -1``) to its own output frame through

    T_parent_out_i = placement_i @ joint_transform_i(q_i)

(``placement_i`` is fixed: the joint's input frame in its parent's output
frame). Kinds, their configuration and velocity sizes and their motion
subspace ``S_i`` (the body twist of the output frame relative to the input
frame is ``S_i v_i``, expressed in the output frame):

| kind      | nq | nv | joint transform            | S (output frame)          |
|-----------|----|----|----------------------------|---------------------------|
| fixed     | 0  | 0  | identity                   | -                         |
| revolute  | 1  | 1  | rotation by q about axis   | [0; axis]                 |
| prismatic | 1  | 1  | translation q along axis   | [axis; 0]                 |
| spherical | 4  | 3  | rotation of the unit quaternion [x, y, z, w] | [0; I]  |
| free      | 7  | 6  | [position; quaternion]     | I (body twist [v; w])     |
| soft      | k  | k  | exp(L f) (or cay(L f))     | L T(L f) B                |

A *soft* joint is one PCS section of length L: its strain f (6-vector,
[axial, shear_y, shear_z, torsion, bending_y, bending_z], in the section's
frame) has k free modes (the columns of B select them; the others stay at the
reference strain f0), and q_i holds the free modes. Its mass is distributed:
Gauss quadrature points at abscissae x_p in [0, L] ride on it with pose
exp(x_p f) relative to its input frame and subspace x_p T(x_p f) B. The
output frame is the section's end cross-section. Rigid joints carry a rigid
body (spatial inertia about their output frame; zero for a massless joint).

Every joint has a joint-space stiffness and damping block (soft sections:
``B^T L K B`` and ``B^T L D B`` from the cross-section's K and D per length;
rigid 1-dof joints: optional passive spring and damper), acting on
``q_i - q0_i`` and ``v_i``. ``q0`` is the reference configuration (the free
part of f0 for soft joints). An *elastic field* (:class:`ElasticField`,
``Model.elastic_fields``) replaces the blocks of the soft joints it covers
by one energy over them all, ``z^T K z / 2`` in ``z = P (q - q0)`` (and the
power ``zdot^T D zdot``): a variable-strain segment's own elasticity, when
its sections are the integration points of a field rather than pieces with
an energy of their own (:mod:`soft_twin_core.robot.soft_chain`). A *field
pair* (:class:`FieldPair`, ``Model.field_pairs``) says that two consecutive
sections' strains are fixed combinations of a field at the 2-point Gauss
points of their joint span: the actuators' quadrature there reads the
field at those points, not the sections' strains.

*Paths* (``Model.paths``) are chains of consecutive soft joints along which
an arc length s [m] is measured (a soft member or a whole soft arm across
rigid offsets); loads and actuators (tendons, chambers) are placed on a path
by arc length. A robot file of the classic schema (one chain of segments)
becomes one path, ``"backbone"`` (:func:`soft_twin_core.robot.soft_chain.robot_tree`).

Units SI; twists, strains and wrenches ``[linear; angular]`` in body frames
(docs/CONVENTIONS.md).
"""

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from soft_twin_core.engine.joint_kinds import (FREE, JOINT_KINDS, NQ as _NQ, NV as _NV, PRISMATIC, REVOLUTE,
                                               SOFT, SPHERICAL)
from soft_twin_core.engine.kernels.data import kernel_struct, pack_model
from soft_twin_core.errors import ModelError
from soft_twin_core.lie import hat


@dataclass(frozen=True, eq=False)
class SoftSection:
    """One PCS section: length L [m], stiffness K and damping D per unit
    length (6x6, on [linear; angular] strains: N, N m^2; N s, N m^2 s),
    inertia density Mc (6x6: kg/m, kg m), reference strain f0, free-mode mask,
    kinematic map ("exponential" or "cayley"), Gauss points per section."""
    length: float
    K: np.ndarray
    D: np.ndarray
    Mc: np.ndarray
    f0: np.ndarray
    free: np.ndarray
    kinematic_map: str = "exponential"
    quadrature_points: int = 2
    quadrature: tuple = None    # (abscissae [m] in [0, L], weights [m]) of the mass; None: Gauss-Legendre

    @cached_property
    def mass_points(self):
        """(abscissae [m], weights [m]) where the section's inertia density
        is integrated: :attr:`quadrature`, or Gauss-Legendre with
        :attr:`quadrature_points` points."""
        if self.quadrature is not None:
            return tuple(np.asarray(a, dtype=float) for a in self.quadrature)
        x, w = np.polynomial.legendre.leggauss(self.quadrature_points)
        return 0.5 * self.length * (x + 1.0), 0.5 * self.length * w

    @cached_property
    def modes(self):
        """Indices (0..5) of the free strain modes: the columns of B (read-only)."""
        out = np.flatnonzero(self.free)
        out.setflags(write=False)
        return out


@dataclass(frozen=True, eq=False)
class Joint:
    """A joint and the body after it (see the module docstring).

    ``inertia``: 6x6 spatial inertia of the rigid body about the output frame
    ([[m I, -m hat(c)], [m hat(c), Ic - m hat(c)^2]], c = centre of mass);
    zero for soft joints. ``stiffness``/``damping``: passive spring [N m/rad or
    N/m] and damper of 1-dof joints; ``limits``: (lower, upper) for 1-dof
    joints (None = unlimited)."""
    name: str
    kind: int
    parent: int
    placement: np.ndarray
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))
    section: SoftSection = None
    stiffness: float = 0.0
    damping: float = 0.0
    q_ref: float = 0.0
    limits: tuple = None

    @property
    def nq(self):
        return len(self.section.modes) if self.kind == SOFT else _NQ[self.kind]

    @property
    def nv(self):
        return len(self.section.modes) if self.kind == SOFT else _NV[self.kind]


@dataclass(frozen=True, eq=False)
class ElasticField:
    """One elastic energy over several soft joints (module docstring): the
    coordinates ``z = P (q - q0)`` of the joints ``joints``' free strains
    (P: (nz, sum of their nv), their coordinates in the joints' order), the
    energy ``z^T K z / 2`` and the dissipation ``zdot^T D zdot / 2`` (K, D:
    (nz, nz), symmetric). The joints' own stiffness and damping blocks are
    then zero. Generalised forces ``P^T (K z + D zdot)``."""
    joints: tuple
    P: np.ndarray
    K: np.ndarray
    D: np.ndarray


@dataclass(frozen=True, eq=False)
class FieldPair:
    """Two consecutive soft joints ``joints`` (the halves of one interval
    of a fourth-order step) whose strains s_1, s_2 are combinations of a
    field xi at the 2-point Gauss points Y_1 < Y_2 of their joint span:
    ``(xi(Y_1), xi(Y_2)) = field @ (s_1, s_2)`` (``field`` (2, 2), the
    inverse of the combination)."""
    joints: tuple
    field: np.ndarray


@dataclass(frozen=True, eq=False)
class Frame:
    """A named frame on joint ``joint``'s body: for soft joints at abscissa
    ``x`` [m] in the section (0 = its input frame), then ``placement``; for
    rigid joints ``placement`` in the output frame."""
    name: str
    joint: int
    placement: np.ndarray
    x: float = 0.0


@dataclass(frozen=True, eq=False)
class Path:
    """Consecutive soft joints (each the child of the previous, possibly
    through fixed joints in between) along which arc length s is measured."""
    name: str
    joints: tuple
    s_starts: np.ndarray
    lengths: np.ndarray

    @property
    def length(self):
        return float(self.s_starts[-1] + self.lengths[-1])

    def locate(self, s):
        """(joint indices, abscissae x in [0, L]) of arc lengths s [m]; a
        boundary belongs to the later section, s = length to the last."""
        s = np.asarray(s, dtype=float)
        if np.any(s < -1e-12) or np.any(s > self.length + 1e-12):
            raise ValueError(f"s: arc lengths on path {self.name!r} must lie in [0, {self.length}] m, "
                             f"got min {np.min(s)}, max {np.max(s)}")
        k = np.clip(np.searchsorted(self.s_starts, s, side="right") - 1, 0, len(self.joints) - 1)
        x = np.clip(s - self.s_starts[k], 0.0, self.lengths[k])
        return np.asarray(self.joints, dtype=np.int64)[k], x


@dataclass(frozen=True, eq=False)
class Model:
    """Immutable multibody model. Build with :class:`ModelBuilder` or
    :func:`soft_twin_core.robot.soft_chain.robot_tree`; algorithms take ``(model, workspace, q, ...)``
    and never modify it."""
    name: str
    joints: tuple
    gravity: np.ndarray
    frames: tuple = ()
    paths: tuple = ()
    actuators: tuple = ()          # soft_twin_core.robot.model.Actuator, placed on paths[actuator_path]
    actuator_path: int = 0
    actuator_paths: tuple = ()     # per actuator, the index of its path (empty: all on actuator_path)
    elastic_fields: tuple = ()     # ElasticField: energies over several soft joints
    field_pairs: tuple = ()        # FieldPair: sections whose strains combine a field's values
    # derived
    nq: int = field(init=False)
    nv: int = field(init=False)
    idx_q: np.ndarray = field(init=False)
    idx_v: np.ndarray = field(init=False)
    parents: np.ndarray = field(init=False)
    kinds: np.ndarray = field(init=False)
    q0: np.ndarray = field(init=False)

    def __post_init__(self):
        set_ = object.__setattr__
        iq, iv, nq, nv = [], [], 0, 0
        for i, j in enumerate(self.joints):
            if not -1 <= j.parent < i:
                raise ModelError(f"joints[{i}] ({j.name}): parent must be -1 or an earlier joint, got {j.parent}")
            iq.append(nq)
            iv.append(nv)
            nq += j.nq
            nv += j.nv
        set_(self, "nq", nq)
        set_(self, "nv", nv)
        set_(self, "idx_q", np.array(iq, dtype=np.int64))
        set_(self, "idx_v", np.array(iv, dtype=np.int64))
        set_(self, "parents", np.array([j.parent for j in self.joints], dtype=np.int64))
        set_(self, "kinds", np.array([j.kind for j in self.joints], dtype=np.int64))
        set_(self, "q0", neutral(self))
        for a in (self.idx_q, self.idx_v, self.parents, self.kinds, self.q0, self.gravity):
            a.setflags(write=False)

    @property
    def n_joints(self):
        return len(self.joints)

    # derived data made on first use and kept (functools.cached_property: the
    # frozen dataclass's __dict__, no __setattr__); the model never changes
    @cached_property
    def arrays(self):
        """The packed arrays of the compiled passes (:class:`kernels.data.ModelArrays`)."""
        return pack_model(self)

    @cached_property
    def kernel_arrays(self):
        """:attr:`arrays` as the compiled passes take them (a structref of the same arrays)."""
        return kernel_struct(self.arrays)

    @cached_property
    def mass_and_size(self):
        """(total mass [kg], size [m]): the rigid bodies' and soft sections'
        mass; the soft paths' lengths plus the joints' placement offsets."""
        a = self.arrays
        mass = float(np.sum(a.inertia[:, 0, 0] * a.rigid_mass) + np.sum(a.mc[:, 0] * a.pw.sum(axis=1)))
        size = float(np.sum(a.length) + np.sum(np.linalg.norm(a.placement[:, :3, 3], axis=1)))
        return mass, size

    def joint_index(self, name):
        for i, j in enumerate(self.joints):
            if j.name == name:
                return i
        raise KeyError(f"no joint named {name!r}")

    def frame_index(self, name):
        for i, f in enumerate(self.frames):
            if f.name == name:
                return i
        raise KeyError(f"no frame named {name!r}")

    def path(self, name="backbone"):
        for p in self.paths:
            if p.name == name:
                return p
        raise KeyError(f"no path named {name!r}")

    @cached_property
    def soft_joints(self):
        return tuple(i for i, j in enumerate(self.joints) if j.kind == SOFT)

    @property
    def actuator_names(self):
        return tuple(a.name for a in self.actuators)

    def path_of_actuator(self, k):
        """The path actuator k is routed on."""
        return self.paths[self.actuator_paths[k] if self.actuator_paths else self.actuator_path]

    def check_q(self, q, name="q"):
        return _check_vector(q, self.nq, name)

    def check_v(self, v, name="v"):
        return _check_vector(v, self.nv, name)

    def subtree(self, i):
        """Joint indices of the subtree rooted at joint i (i included)."""
        out = [i]
        for k in range(i + 1, self.n_joints):
            if self.joints[k].parent in out:
                out.append(k)
        return out

    def support(self, i):
        """Joint indices from the root to joint i (i included)."""
        out = []
        while i >= 0:
            out.append(i)
            i = self.joints[i].parent
        return out[::-1]


def _check_vector(x, n, name):
    x = np.asarray(x)
    if x.dtype.kind not in "fc":
        x = x.astype(float)
    if x.shape != (n,):
        raise ValueError(f"{name}: expected shape ({n},) for this model, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: contains NaN or inf")
    return x


def neutral(model):
    """The reference configuration q0: f0's free modes for soft joints, the
    identity quaternion for spherical/free joints, q_ref for 1-dof joints."""
    q = np.zeros(model.nq)
    for i, j in enumerate(model.joints):
        a = model.idx_q[i]
        if j.kind == SOFT:
            q[a:a + j.nq] = j.section.f0[j.section.modes]
        elif j.kind == SPHERICAL:
            q[a + 3] = 1.0
        elif j.kind == FREE:
            q[a + 6] = 1.0
        elif j.kind in (REVOLUTE, PRISMATIC):
            q[a] = j.q_ref
    return q


# ----------------------------------------------------------------------------
# Rigid inertia
# ----------------------------------------------------------------------------

def spatial_inertia(mass, com=(0.0, 0.0, 0.0), inertia_com=None):
    """6x6 spatial inertia about a body frame, [linear; angular] order:
    ``[[m I, -m hat(c)], [m hat(c), Ic - m hat(c)^2]]``; ``inertia_com`` is the
    3x3 rotational inertia about the centre of mass c (body axes) [kg m^2]."""
    c = np.asarray(com, dtype=float)
    Ic = np.zeros((3, 3)) if inertia_com is None else np.asarray(inertia_com, dtype=float)
    C = hat(c)
    out = np.zeros((6, 6))
    out[:3, :3] = mass * np.eye(3)
    out[:3, 3:] = -mass * C
    out[3:, :3] = mass * C
    out[3:, 3:] = Ic - mass * C @ C
    return out


# ----------------------------------------------------------------------------
# Builder
# ----------------------------------------------------------------------------

class ModelBuilder:
    """Adds joints in topological order and returns an immutable Model.

    >>> b = ModelBuilder("pan_tilt_arm", gravity=(0, 0, -9.81))
    >>> pan = b.add_joint("pan", "revolute", parent=-1, axis=(0, 0, 1))
    """

    def __init__(self, name="robot", gravity=(0.0, 0.0, -9.81)):
        self.name = name
        self.gravity = np.asarray(gravity, dtype=float)
        self.joints, self.frames, self.paths = [], [], []
        self.actuators, self.actuator_path, self.actuator_paths = (), 0, ()
        self.elastic_fields = []
        self.field_pairs = []

    def add_elastic_field(self, joints, P, K, D):
        """An :class:`ElasticField` over the soft joints ``joints``."""
        joints = tuple(int(j) for j in joints)
        nr = sum(self.joints[j].nv for j in joints)
        P, K, D = (np.array(a, dtype=float) for a in (P, K, D))
        if P.ndim != 2 or P.shape[1] != nr or K.shape != (P.shape[0],) * 2 or D.shape != K.shape:
            raise ModelError(f"elastic field over joints {joints}: P must be (nz, {nr}) and K, D (nz, nz), got "
                             f"{P.shape}, {K.shape}, {D.shape}")
        if any(self.joints[j].kind != SOFT for j in joints):
            raise ModelError(f"elastic field over joints {joints}: only soft joints")
        self.elastic_fields.append(ElasticField(joints, P, K, D))

    def add_field_pair(self, j1, j2, field):
        """A :class:`FieldPair` of the soft joints j1 and its child j2."""
        if self.joints[j2].parent != j1 or SOFT != self.joints[j1].kind or SOFT != self.joints[j2].kind:
            raise ModelError(f"field pair ({j1}, {j2}): expected a soft joint and its soft child")
        self.field_pairs.append(FieldPair((int(j1), int(j2)), np.array(field, dtype=float).reshape(2, 2)))

    def add_joint(self, name, kind, parent=-1, placement=None, axis=(0, 0, 1), inertia=None,
                  section=None, stiffness=0.0, damping=0.0, q_ref=0.0, limits=None):
        kind = JOINT_KINDS.index(kind) if isinstance(kind, str) else int(kind)
        if name in (j.name for j in self.joints):
            raise ModelError(f"joint {name!r}: names must be unique")
        axis = np.asarray(axis, dtype=float)
        if kind in (REVOLUTE, PRISMATIC):
            nrm = np.linalg.norm(axis)
            if not np.isfinite(nrm) or nrm == 0:
                raise ModelError(f"joint {name!r}.axis: expected a non-zero 3-vector, got {axis.tolist()}")
            axis = axis / nrm
        if kind == SOFT and section is None:
            raise ModelError(f"joint {name!r}: a soft joint needs a section")
        self.joints.append(Joint(name, kind, int(parent),
                                 np.eye(4) if placement is None else np.asarray(placement, dtype=float),
                                 axis, np.zeros((6, 6)) if inertia is None else np.asarray(inertia, float),
                                 section, float(stiffness), float(damping), float(q_ref), limits))
        return len(self.joints) - 1

    def add_soft_chain(self, name, sections, parent=-1, placement=None, between=None):
        """Consecutive soft joints ``name_0, name_1, ...``; ``between[k]`` is
        the placement of section k+1 after section k (rigid offsets)."""
        out = []
        for k, sec in enumerate(sections):
            pl = placement if k == 0 else (None if between is None else between[k - 1])
            parent = self.add_joint(f"{name}_{k}", SOFT, parent, pl, section=sec)
            out.append(parent)
        return out

    def add_path(self, name, joints):
        lengths = np.array([self.joints[j].section.length for j in joints])
        self.paths.append(Path(name, tuple(int(j) for j in joints),
                               np.concatenate([[0.0], np.cumsum(lengths)[:-1]]), lengths))
        return len(self.paths) - 1

    def add_frame(self, name, joint, placement=None, x=0.0):
        self.frames.append(Frame(name, int(joint), np.eye(4) if placement is None else
                                 np.asarray(placement, dtype=float), float(x)))
        return len(self.frames) - 1

    def build(self):
        return Model(self.name, tuple(self.joints), self.gravity.copy(), tuple(self.frames),
                     tuple(self.paths), tuple(self.actuators), self.actuator_path,
                     tuple(self.actuator_paths), tuple(self.elastic_fields), tuple(self.field_pairs))
