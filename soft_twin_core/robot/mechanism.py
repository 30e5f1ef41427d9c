"""Soft articulated robots: the tree robot file, joint control and constraints.

A *mechanism* is a multibody tree (:class:`multibody.Model`) plus what a
user says about it beyond the tree itself:

* which rigid joints are *effort-controlled* (their force or torque is an
  input, like a tendon tension) and which are *position-controlled* (their
  position follows a command; their effort is an output, the Lagrange
  multiplier of the motion constraint, i.e. inverse dynamics);
* *constraints* between two frames, or a frame and the world (closed chains
  and boundary conditions): ``clamped`` (6 dof), ``pinned`` (position),
  ``line`` (the point slides on a world line) and ``plane`` (on a world
  plane); :mod:`soft_twin_core.solve.constrained` solves statics and dynamics with
  them;
* the cross-section geometry of every soft section, for stresses.

The robot file of a mechanism has a ``bodies`` list (see
:func:`mechanism_from_dict` and the README, "Soft articulated robots"); a
classic file (``segments``: one soft chain) becomes a mechanism with no
rigid joints through :func:`from_robot_model`. Units SI; frames and wrench
conventions of docs/CONVENTIONS.md.
"""

from dataclasses import dataclass, field, replace
import warnings

import numpy as np

from soft_twin_core.limits import (MAX_BODIES, MAX_SECTIONS_PER_SEGMENT, MAX_SECTIONS_TOTAL, check_limit,
                                   read_text)
from soft_twin_core.robot import plausibility

from soft_twin_core.engine import algorithms as alg
from soft_twin_core.engine.joint_kinds import FIXED, FREE, PRISMATIC, REVOLUTE, RIGID_JOINT_TYPES, SPHERICAL
from soft_twin_core.engine.multibody import ModelBuilder, spatial_inertia
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.robot.model import (ModelError, _check_keys, _num, _vec, find_file, model_from_dict,
                                        pose_from_dict, read_yaml_file, robot_mapping)
from soft_twin_core.robot.obstacles import (contact_spacing, link_shape, member_capsules, member_contact,
                                            obstacles_from_list)
from soft_twin_core.robot.soft_chain import add_member
from soft_twin_core.robot.strain_bases import SegmentBasis, robot_basis
from soft_twin_core.robot.stress import section_geometry
from soft_twin_core.robot.urdf import bodies_from_urdf

CONSTRAINT_TYPES = {"clamped": 6, "pinned": 3, "line": 2, "plane": 1}
JOINT_TYPES = RIGID_JOINT_TYPES
CONTROL_MODES = ("effort", "position", "passive")


@dataclass(frozen=True, eq=False)
class PointRef:
    """A point of the tree: joint ``joint`` at abscissa ``x`` [m] of its soft
    section, or its output frame (``x = -1``). ``joint = -1`` is the world."""
    joint: int
    x: float = -1.0


@dataclass(frozen=True, eq=False)
class Constraint:
    """A holonomic constraint of frame ``a`` on frame ``b`` (``b.joint == -1``:
    the world, at the pose ``target``, which a trajectory may move).

    Rows in world axes: ``clamped`` [p_a - p_b; log(R_a R_b^T)] (6), ``pinned``
    p_a - p_b (3), ``line`` N (p_a - p_b) with N the two unit normals of
    ``direction`` (2), ``plane`` n . (p_a - p_b) (1). The reaction on a is the
    world wrench W = C^T lambda at a's origin ([force; moment], C the rows'
    directions), -W on b."""
    name: str
    kind: str
    a: PointRef
    b: PointRef
    target: np.ndarray = field(default_factory=lambda: np.eye(4))
    direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def size(self):
        return CONSTRAINT_TYPES[self.kind]

    def rows(self):
        """C (size, 6): the directions of the multipliers in the world wrench (read-only)."""
        C = self.__dict__.get("_rows")
        if C is None:
            C = self._make_rows()
            C.setflags(write=False)
            object.__setattr__(self, "_rows", C)
        return C

    def _make_rows(self):
        C = np.zeros((self.size, 6))
        if self.kind == "clamped":
            C[:] = np.eye(6)
        elif self.kind == "pinned":
            C[:, :3] = np.eye(3)
        elif self.kind == "line":
            C[:, :3] = _normals(self.direction)
        else:
            C[0, :3] = self.direction
        return C


def _normals(d):
    """Two unit vectors orthogonal to the unit vector d (and to each other)."""
    e = np.eye(3)[np.argmin(np.abs(d))]
    n1 = np.cross(d, e)
    n1 /= np.linalg.norm(n1)
    return np.array([n1, np.cross(d, n1)])


@dataclass(frozen=True, eq=False)
class Member:
    """A soft member: consecutive soft joints (a path of the tree) with its
    cross-section geometry per section (None: given by ``sectional``) and
    the name of the robot file's segment each belongs to (a fourth-order
    segment has 4n + 2 of them for its n sections: soft_chain)."""
    name: str
    path: int
    joints: tuple
    geometry: tuple
    segments: tuple = ()


@dataclass(frozen=True, eq=False)
class Link:
    """A rigid link: the body of joint ``joint``, with a visual shape
    (dict: shape box/cylinder/sphere and sizes [m]) for display."""
    name: str
    joint: int
    visual: dict = None
    collision: object = None       # engine.contact.Obstacle in the link's frame (body = joint), or None


@dataclass(frozen=True, eq=False)
class Mechanism:
    """A soft articulated robot: the tree, its joint control modes,
    constraints, members and links. Immutable."""
    name: str
    tree: object
    control: tuple                 # per joint: "effort", "position", "passive" or "" (soft/fixed)
    constraints: tuple = ()
    members: tuple = ()
    links: tuple = ()
    frames: dict = field(default_factory=dict)   # name -> PointRef
    base_motion: str = "fixed"     # fixed, floating or prescribed
    motion_limits: dict = field(default_factory=dict)   # position-controlled joint -> (max vel, max acc)
    base_pose: np.ndarray = field(default_factory=lambda: np.eye(4))   # world <- base (the file's base)
    obstacles: tuple = ()          # engine.contact.Obstacle: what the members touch (robot/obstacles.py)
    contact_spacing: float = None  # [m] between contact points (None: robot.obstacles.contact_points' default)
    member_shapes: tuple = ()      # capsules along members that others touch (robot.obstacles.member_capsules)
    strain_bases: tuple = ()       # strain_bases.SegmentBasis: the variable-strain segments (none: PCS)

    @property
    def basis(self):
        """B (nv, nz), read-only, of the robot's coordinates z, ``q = q0 + B
        z`` (:func:`strain_bases.robot_basis`), or None when no segment has a
        strain basis (then the coordinates are q). Cached."""
        if not self.strain_bases:
            return None
        out = self.__dict__.get("_basis")
        if out is None:
            out = robot_basis(self.tree, self.strain_bases)
            object.__setattr__(self, "_basis", out)
        return out[0]

    @property
    def coordinate_names(self):
        """The names of the coordinates z (:attr:`basis`'s columns)."""
        return () if self.basis is None else self.__dict__["_basis"][1]

    @property
    def shapes(self):
        """The obstacles the robot carries (engine.contact.Obstacle on its joints' frames; cached): the
        links' collision shapes, then the capsules along members that others touch."""
        out = self.__dict__.get("_shapes")
        if out is None:
            out = tuple(lk.collision for lk in self.links if lk.collision is not None) + tuple(self.member_shapes)
            object.__setattr__(self, "_shapes", out)
        return out

    @property
    def actuators(self):
        return self.tree.actuators

    @property
    def actuator_names(self):
        return self.tree.actuator_names

    def joints_with(self, mode):
        """Indices of the rigid joints of control mode ``mode`` (cached)."""
        cache = self.__dict__.setdefault("_joints_with", {})
        out = cache.get(mode)
        if out is None:
            out = cache[mode] = tuple(i for i, c in enumerate(self.control) if c == mode)
        return out

    @property
    def rigid_joints(self):
        """Indices of the 1-dof rigid joints (revolute, prismatic): those a
        JointState names."""
        return tuple(i for i, j in enumerate(self.tree.joints) if j.kind in (REVOLUTE, PRISMATIC))

    @property
    def joint_names(self):
        return tuple(self.tree.joints[i].name for i in self.rigid_joints)

    def frame(self, name):
        """The PointRef of a named frame, or of a point of a soft member at
        arc length s [m] from its base, ``"<member>@<s>"`` (KeyError naming
        what is wrong)."""
        if name in self.frames:
            return self.frames[name]
        if isinstance(name, str) and "@" in name:
            return self.member_point(*name.rsplit("@", 1))
        raise KeyError(f"no frame named {name!r}; this robot has {sorted(self.frames)}, and the points "
                       f"'<member>@<s>' of its members {[m.name for m in self.members]} (s in m)")

    def member_point(self, member, s):
        """PointRef of member ``member``'s point at arc length ``s`` [m] (a
        number or its text) from the member's base, within its length."""
        m = self.member(member)
        try:
            s = float(s)
        except (TypeError, ValueError):
            raise KeyError(f"{member}@{s}: the arc length must be a number of metres") from None
        lengths = [self.tree.joints[j].section.length for j in m.joints]
        total = float(sum(lengths))
        if not (np.isfinite(s) and -1e-6 <= s <= total + 1e-6):
            raise KeyError(f"{member}@{s:g}: the arc length must lie in [0, {total:g}] m (member {member!r})")
        for j, L in zip(m.joints, lengths):
            if s <= L or j == m.joints[-1]:
                return PointRef(j, float(min(max(s, 0.0), L)))
            s -= L

    def member(self, name):
        for m in self.members:
            if m.name == name:
                return m
        raise KeyError(f"no member named {name!r}; this robot has {[m.name for m in self.members]}")

    @property
    def n_constraint_rows(self):
        return sum(c.size for c in self.constraints)


# ----------------------------------------------------------------------------
# Robot file
# ----------------------------------------------------------------------------

_BODY_KEYS = {"name", "type", "parent", "joint", "mass", "com", "inertia", "visual", "collision", "segments",
              "actuators"}
_JOINT_KEYS = {"name", "type", "axis", "position", "rpy", "quaternion", "limits", "stiffness", "damping",
               "reference", "control", "max_velocity", "max_acceleration"}
# speed and acceleration bounds of a position-controlled joint's motion towards
# a new command (rad/s, rad/s^2 or m/s, m/s^2) when the robot file gives none
DEFAULT_MAX_VELOCITY, DEFAULT_MAX_ACCELERATION = 1.0, 10.0
_FRAME_KEYS = {"name", "body", "s", "position", "rpy", "quaternion"}
_CONSTRAINT_KEYS = {"name", "type", "frame", "to", "target", "direction", "normal"}


def check_joint_position(joint, value):
    """None if ``value`` (rad or m) lies within the joint's declared
    ``limits`` (or it declares none), else ("over_limit", message). The
    one rule for the node's joint commands and the offline scenario runner."""
    lim = joint.limits
    if lim is not None and not lim[0] <= value <= lim[1]:
        return "over_limit", f"joint {joint.name} position {value:g} lies outside the joint limits {list(lim)}"
    return None


def base_targets(mech, pose):
    """The constraints' world targets with a prescribed base at ``pose``
    (4x4; None: every constraint's own): the ``targets`` of the solvers."""
    if pose is None:
        return None
    return [pose if c.name == "base" else None for c in mech.constraints]


def tip_frame(mech):
    """The frame that is the robot's tip (the node's ``~/tip_pose``, the
    default of the planner and of the workspace map): ``tip`` if the robot
    has one (every classic rod has), else ``tool``, else the last soft
    member's end (``<member>_tip``), else its last frame."""
    for name in ("tip", "tool") + ((f"{mech.members[-1].name}_tip",) if mech.members else ()):
        if name in mech.frames:
            return name
    return list(mech.frames)[-1]


def is_tree_file(d):
    """True for a robot mapping of the tree schema (a ``bodies`` list)."""
    return isinstance(d, dict) and "bodies" in d


def is_tree_robot(robot, base_dir="."):
    """True if ``robot`` (a path relative to ``base_dir``, an example
    robot's name, or a mapping) is a tree robot file; False for anything
    else, unreadable files included (their loader reports them)."""
    import os
    if isinstance(robot, dict):
        return is_tree_file(robot)
    if not isinstance(robot, str):
        return False
    p = robot if os.path.isabs(robot) else os.path.join(base_dir, robot)
    if not os.path.isfile(p) and os.path.basename(robot) == robot:
        try:
            p = find_file(robot, "robots")
        except ModelError:
            return False
    try:
        return is_tree_file(robot_mapping(read_yaml_file(p), p))
    except ModelError:
        return False


def load_mechanism(path, sections=None):
    """A :class:`Mechanism` from a robot file of either schema; ``path`` may
    also name an example robot (``load_mechanism("pan_tilt_arm")``);
    ``sections``: a segments robot's sections per segment (its file's by
    default)."""
    import os
    path = find_file(path, "robots")
    d = robot_mapping(read_yaml_file(path, what="robot file"), str(path))
    if is_tree_file(d):
        return mechanism_from_dict(d, os.path.dirname(os.path.abspath(path)))
    return from_robot_model(model_from_dict(d, sections), d, os.path.dirname(os.path.abspath(path)))


def _with_urdf(d, base_dir):
    """The bodies of ``d`` after those of its ``urdf`` file (a path relative
    to ``base_dir``): a rigid robot onto which members are mounted."""
    import os
    path = d["urdf"]
    if not isinstance(path, str) or not path:
        raise ModelError(f"robot.urdf: expected a file path, got {path!r}")
    full = path if os.path.isabs(path) or base_dir is None else os.path.join(base_dir, path)
    text = read_text(full, ModelError, "robot.urdf:")      # size and encoding checked (a binary file)
    return bodies_from_urdf(text, f"robot.urdf ({path})") + list(d.get("bodies") or [])


def _pose(d, where):
    return pose_from_dict({k: d[k] for k in ("position", "rpy", "quaternion") if k in d} or None, where)


def _inertia3(v, where):
    """[ixx, iyy, izz, ixy, ixz, iyz] or a 3x3 list -> symmetric positive semi-definite 3x3."""
    if v is None:
        return np.zeros((3, 3))
    a = np.asarray(v, dtype=float) if not isinstance(v, dict) else None
    if a is None or a.shape not in ((6,), (3, 3)) or not np.all(np.isfinite(a)):
        raise ModelError(f"{where}: expected [ixx, iyy, izz, ixy, ixz, iyz] (kg m^2, about the centre of "
                         f"mass, link axes) or a 3x3 matrix, got {v!r}")
    if a.shape == (6,):
        xx, yy, zz, xy, xz, yz = a
        a = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
    if np.abs(a - a.T).max() > 1e-12 * max(1.0, np.abs(a).max()):
        raise ModelError(f"{where}: the inertia matrix must be symmetric")
    ev = np.linalg.eigvalsh(a)
    if ev.min() < -1e-12 * max(1.0, ev.max()) or (ev.sum() - 2 * ev.max()) < -1e-9 * max(1e-30, ev.max()):
        raise ModelError(f"{where}: not a physical inertia (eigenvalues {ev.tolist()} must be >= 0 and "
                         f"satisfy the triangle inequality)")
    return a


def _visual(v, where):
    if v is None:
        return None
    _check_keys(v, {"shape", "size", "radius", "length", "position", "rpy"}, where)
    shape = v.get("shape", "box")
    if shape == "box":
        _vec(v, "size", 3, where)
    elif shape == "cylinder":
        _num(v, "radius", where, positive=True)
        _num(v, "length", where, positive=True)
    elif shape == "sphere":
        _num(v, "radius", where, positive=True)
    else:
        raise ModelError(f"{where}.shape: expected box, cylinder or sphere, got {shape!r}")
    return dict(v)


def _joint(b, jd, where, default_name, is_member):
    """(name, kind, placement, axis, limits, stiffness, damping, reference, control, (max velocity, max
    acceleration) or None) of a body's joint."""
    jd = {} if jd is None else jd
    _check_keys(jd, _JOINT_KEYS, where)
    kind_name = jd.get("type", "fixed")
    if kind_name not in JOINT_TYPES:
        raise ModelError(f"{where}.type: expected one of {sorted(JOINT_TYPES)}, got {kind_name!r}")
    kind = JOINT_TYPES[kind_name]
    if kind == FREE and is_member:
        raise ModelError(f"{where}.type: a free member is not supported (a free link is: a loose object; a "
                         f"floating robot: give base: {{motion: floating}})")
    name = jd.get("name", default_name)
    if not isinstance(name, str) or not name:
        raise ModelError(f"{where}.name: expected a non-empty string, got {name!r}")
    placement = _pose(jd, where)
    axis = _vec(jd, "axis", 3, where, default=[0, 0, 1])
    if kind in (REVOLUTE, PRISMATIC) and not np.linalg.norm(axis) > 0:
        raise ModelError(f"{where}.axis: expected a non-zero 3-vector, got {axis.tolist()}")
    limits = None
    if jd.get("limits") is not None:
        lim = _vec(jd, "limits", 2, where)
        if not lim[0] < lim[1]:
            raise ModelError(f"{where}.limits: need lower < upper, got {lim.tolist()}")
        limits = (float(lim[0]), float(lim[1]))
        if kind == REVOLUTE:
            plausibility.check_revolute_limits(where, limits, ModelError)
    stiffness = _num(jd, "stiffness", where, nonneg=True, default=0.0)
    damping = _num(jd, "damping", where, nonneg=True, default=0.0)
    reference = _num(jd, "reference", where, default=0.0)
    if kind == REVOLUTE:
        plausibility.check_angles(f"{where}.reference", (reference,))
    control = ""
    motion = None
    if kind in (REVOLUTE, PRISMATIC):
        control = jd.get("control", "effort")
        if control not in CONTROL_MODES:
            raise ModelError(f"{where}.control: expected one of {list(CONTROL_MODES)}, got {control!r}")
        for key in ("max_velocity", "max_acceleration"):
            if key in jd and control != "position":
                raise ModelError(f"{where}.{key}: only position-controlled joints take {key}")
        motion = (_num(jd, "max_velocity", where, positive=True, default=DEFAULT_MAX_VELOCITY),
                  _num(jd, "max_acceleration", where, positive=True, default=DEFAULT_MAX_ACCELERATION))
        if limits is not None and not limits[0] <= reference <= limits[1]:
            raise ModelError(f"{where}.reference: {reference} lies outside the limits {list(limits)}")
    else:
        for key in ("limits", "stiffness", "damping", "reference", "control", "max_velocity", "max_acceleration"):
            if key in jd:
                raise ModelError(f"{where}.{key}: only revolute and prismatic joints take {key}")
    if is_member and kind not in (FIXED, REVOLUTE, PRISMATIC, SPHERICAL):
        raise ModelError(f"{where}.type: unsupported for a member")
    return name, kind, placement, axis, limits, stiffness, damping, reference, control, motion


def _member_geometry(segments, robot):
    """Per-section SectionGeometry (None where a segment gives ``sectional``),
    each segment's for as many sections as the model gives it (the file's
    ``sections``, or the same count for every segment when the model was
    built with a section-count override)."""
    counts = [int(sd.get("sections", 1)) for sd in segments]
    if sum(counts) != robot.n_sections and segments and robot.n_sections % len(segments) == 0:
        counts = [robot.n_sections // len(segments)] * len(segments)      # model_from_dict's override
    out = []
    for sd, n in zip(segments, counts):
        g = section_geometry(sd["cross_section"]) if "cross_section" in sd else None
        out += [g] * n
    return out


def mechanism_from_dict(d, base_dir=None):
    """A :class:`Mechanism` from the tree schema::

        name, gravity, kinematic_map, quadrature_points   # as the classic schema
        base: {position, rpy | quaternion, motion: fixed | floating | prescribed}
        bodies:            # in order: a parent comes before its children
          - name: pan_link
            type: link                    # rigid: mass [kg], com [m], inertia [kg m^2] about the com
            parent: base                  # "base" or an earlier body (a member: its tip)
            joint: {name, type: fixed|revolute|prismatic|spherical, axis, position, rpy,
                    limits: [lo, hi], stiffness, damping, reference, control: effort|position|passive}
            mass: 0.3
            com: [0, 0, 0.02]
            inertia: [ixx, iyy, izz, ixy, ixz, iyz]
            visual: {shape: box|cylinder|sphere, size | radius, length}
          - name: arm
            type: member                  # soft: segments and actuators as in the classic schema
            parent: pan_link
            joint: {type: fixed, position: [0, 0, 0.05]}
            segments: [...]
            actuators: [...]              # arc lengths along this member
        frames:            # named points: on a member at arc length s [m], or on a link
          - {name: tool, body: arm, s: 0.45, position, rpy}
        constraints:
          - {name, type: clamped | pinned | line | plane, frame: A, to: world | FRAME,
             target: {position, rpy} (world only), direction: [..] (line), normal: [..] (plane)}

        urdf: rigid.urdf   # optional: its links and joints come first (bodies named after its links;
                           # the root link is the base), relative to ``base_dir`` (the file's folder)

    Each member gets a path (its name) and a frame ``<member>_tip`` at its
    end; each link a frame with its own name. Raises ModelError naming the
    field."""
    _check_keys(d, {"name", "base", "gravity", "kinematic_map", "quadrature_points", "bodies", "frames",
                    "constraints", "urdf", "obstacles", "contact"}, "robot")
    kmap = d.get("kinematic_map", "exponential")
    if kmap not in ("exponential", "cayley"):
        raise ModelError(f"robot.kinematic_map: expected 'exponential' or 'cayley', got {kmap!r}")
    npt = d.get("quadrature_points", 2)
    if isinstance(npt, bool) or not isinstance(npt, int) or not 1 <= npt <= 20:
        raise ModelError(f"robot.quadrature_points: expected an integer in 1..20, got {npt!r}")
    base = dict(d.get("base") or {})
    _check_keys(base, {"position", "rpy", "quaternion", "motion"}, "robot.base")
    motion = base.pop("motion", "fixed")
    if motion not in ("fixed", "floating", "prescribed"):
        raise ModelError(f"robot.base.motion: expected fixed, floating or prescribed, got {motion!r}")
    base_pose = pose_from_dict(base or None, "robot.base")
    b = ModelBuilder(str(d.get("name", "robot")), _vec(d, "gravity", 3, "robot", default=[0, 0, -9.81]))
    control = []
    # the base: a massless free joint when it moves, else the world frame at base_pose
    ends = {}                     # body name -> (joint whose output frame is the body's end)
    if motion == "fixed":
        ends["base"] = (-1, base_pose)
    else:
        jb = b.add_joint("base", FREE, -1, base_pose)
        control.append("")
        ends["base"] = (jb, np.eye(4))
    bodies = _with_urdf(d, base_dir) if "urdf" in d else d.get("bodies")
    if not isinstance(bodies, list) or not bodies:
        raise ModelError("robot.bodies: expected a non-empty list of bodies (links and members)")
    check_limit("robot.bodies: number of bodies", len(bodies), MAX_BODIES, ModelError)
    n_soft = 0                    # soft sections of all members (resource bound)
    members, links, frames = [], [], {}
    actuators, act_paths = [], []
    strain_bases = ()
    motion_limits = {}
    if motion != "fixed":
        frames["base"] = PointRef(ends["base"][0])
    for k, bd in enumerate(bodies):
        where = f"bodies[{k}]"
        _check_keys(bd, _BODY_KEYS, where)
        name = bd.get("name")
        if not isinstance(name, str) or not name:
            raise ModelError(f"{where}.name: expected a non-empty string, got {name!r}")
        where = f"bodies[{k}] ({name})"
        if name in ends or name == "world":
            raise ModelError(f"{where}.name: {name!r} is already used")
        btype = bd.get("type")
        if btype not in ("link", "member"):
            raise ModelError(f"{where}.type: expected 'link' or 'member', got {btype!r}")
        parent = bd.get("parent", "base")
        if parent not in ends:
            raise ModelError(f"{where}.parent: {parent!r} is not 'base' or an earlier body; earlier bodies: "
                             f"{[n for n in ends if n != 'base']}")
        pj, pre = ends[parent]
        jname, kind, placement, axis, limits, stiff, damp, ref, ctrl, jmotion = _joint(
            bd, bd.get("joint"), where + ".joint", f"{name}_joint", btype == "member")
        if jname in [j.name for j in b.joints]:
            raise ModelError(f"{where}.joint.name: {jname!r} is already used")
        placement = pre @ placement
        if ctrl == "position":
            motion_limits[jname] = jmotion
        if btype == "link":
            for key in ("segments", "actuators"):
                if key in bd:
                    raise ModelError(f"{where}.{key}: only members have {key}")
            mass = _num(bd, "mass", where, nonneg=True, default=0.0)
            com = _vec(bd, "com", 3, where, default=[0, 0, 0])
            Ic = _inertia3(bd.get("inertia"), where + ".inertia")
            if kind in (REVOLUTE, PRISMATIC, SPHERICAL) and mass == 0.0 and not np.any(Ic):
                pass      # a massless moving link is allowed if something massive follows it
            ji = b.add_joint(jname, kind, pj, placement, axis, spatial_inertia(mass, com, Ic), None,
                             stiff, damp, ref, limits)
            control.append(ctrl)
            if kind == FREE and mass == 0.0:
                raise ModelError(f"{where}.mass: a free link (a loose object) needs a mass > 0 kg")
            links.append(Link(name, ji, _visual(bd.get("visual"), where + ".visual"),
                              link_shape(bd.get("collision"), name, ji, where + ".collision", base_dir)))
            ends[name] = (ji, np.eye(4))
            frames[name] = PointRef(ji)
        else:
            for key in ("mass", "com", "inertia", "visual", "collision"):
                if key in bd:
                    raise ModelError(f"{where}.{key}: a member's inertia comes from its segments; "
                                     f"{key} is for links")
            if kind != FIXED:
                ji = b.add_joint(jname, kind, pj, placement, axis, None, None, stiff, damp, ref, limits)
                control.append(ctrl)
                pj, placement = ji, np.eye(4)
            sub = {"name": name, "segments": bd.get("segments"), "actuators": bd.get("actuators", []),
                   "gravity": [0.0, 0.0, 0.0], "kinematic_map": kmap}
            segs = sub["segments"]
            if isinstance(segs, list):       # the total over all members, before any allocation
                for k_seg, sd in enumerate(segs):
                    n = sd.get("sections", 1) if isinstance(sd, dict) else 1
                    n = n if isinstance(n, int) and not isinstance(n, bool) else 0
                    check_limit(f"{where}.segments[{k_seg}].sections", n, MAX_SECTIONS_PER_SEGMENT, ModelError)
                    n_soft += n
                check_limit("robot: total sections of all members (sum of bodies[*].segments[*].sections)",
                            n_soft, MAX_SECTIONS_TOTAL, ModelError)
            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", plausibility.PlausibilityWarning)
                    robot = model_from_dict(sub)
            except ModelError as e:
                raise ModelError(f"{where}.{e}") from None
            for w in caught:             # the member's warnings, with the body named
                if issubclass(w.category, plausibility.PlausibilityWarning):
                    warnings.warn(f"{where}.{w.message}", plausibility.PlausibilityWarning, stacklevel=2)
                else:
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
            for a in robot.actuators:
                if a.tendon_model == "point_moment":
                    raise ModelError(f"{where}.actuators ({a.name}): the point_moment tendon model is "
                                     f"supported in the classic single-chain schema only")
                if a.name in [x.name for x in actuators]:
                    raise ModelError(f"{where}.actuators: name {a.name!r} is already used")
            js, owners, bases = add_member(b, name, robot, kmap, npt, pj, placement)
            control += [""] * len(js)
            pi = b.add_path(name, js)
            actuators += list(robot.actuators)
            act_paths += [pi] * len(robot.actuators)
            geo = _member_geometry(bd["segments"], robot)
            members.append(Member(name, pi, tuple(js), tuple(geo[o] for o in owners),
                                  tuple(robot.sections[o].segment for o in owners)))
            strain_bases += bases
            ends[name] = (js[-1], robot.sections[-1].offset_after)
            frames[f"{name}_tip"] = PointRef(js[-1], b.joints[js[-1]].section.length)
    b.actuators, b.actuator_paths = tuple(actuators), tuple(act_paths)
    if len({a.name for a in actuators}) != len(actuators):
        raise ModelError("robot: actuator names must be unique across members")
    # named frames: a frame with a placement on a link or a member's end is a massless fixed joint
    fr = d.get("frames") or []
    if not isinstance(fr, list):
        raise ModelError("robot.frames: expected a list")
    check_limit("robot.frames: number of frames", len(fr), MAX_BODIES, ModelError)
    for k, fd in enumerate(fr):
        where = f"frames[{k}]"
        _check_keys(fd, _FRAME_KEYS, where)
        fname = fd.get("name")
        if not isinstance(fname, str) or not fname:
            raise ModelError(f"{where}.name: expected a non-empty string, got {fname!r}")
        if fname in frames or fname == "world":
            raise ModelError(f"{where}.name: {fname!r} is already used")
        body = fd.get("body")
        pl = _pose(fd, where)
        mem = next((m for m in members if m.name == body), None)
        lnk = next((lk for lk in links if lk.name == body), None)
        if mem is None and lnk is None:
            raise ModelError(f"{where}.body: {body!r} is not a body of this robot")
        if mem is not None:
            path = b.paths[mem.path]
            s = _num(fd, "s", where, nonneg=True, default=path.length)
            if s > path.length + 1e-12:
                raise ModelError(f"{where}.s: {s} m is beyond the member's length {path.length} m")
            j, x = path.locate(min(s, path.length))
            j, x = int(j), float(x)
            if np.abs(pl - np.eye(4)).max() == 0:
                frames[fname] = PointRef(j, x)
                continue
            if abs(x - b.joints[j].section.length) > 1e-12:
                raise ModelError(f"{where}: a frame with a placement on a member must be at its end or a "
                                 f"section end (s = {path.s_starts[1:].tolist() + [path.length]})")
            parent_joint = j
        else:
            if "s" in fd:
                raise ModelError(f"{where}.s: only frames on members take an arc length")
            parent_joint = lnk.joint
        ji = b.add_joint(fname, FIXED, parent_joint, pl)
        control.append("")
        frames[fname] = PointRef(ji)
    tree = b.build()
    constraints = _with_targets(tree, _constraints(d.get("constraints") or [], frames, motion))
    if motion == "prescribed":
        # the base follows a trajectory: a clamp of its frame to a moving world target
        if any(c.name == "base" for c in constraints):
            raise ModelError("robot.constraints: the name 'base' is taken by the prescribed base motion")
        constraints.insert(0, Constraint("base", "clamped", frames["base"], PointRef(-1), base_pose.copy()))
    mech = Mechanism(tree.name, tree, tuple(control), tuple(constraints), tuple(members), tuple(links),
                     frames, motion, motion_limits, np.array(base_pose, dtype=float),
                     strain_bases=strain_bases, **_contact_fields(d, tree, members, base_dir))
    return mech


def _constraints(cl, frames, motion):
    if not isinstance(cl, list):
        raise ModelError("robot.constraints: expected a list")
    check_limit("robot.constraints: number of constraints", len(cl), MAX_BODIES, ModelError)
    out = []
    names = set()
    for k, cd in enumerate(cl):
        where = f"constraints[{k}]"
        _check_keys(cd, _CONSTRAINT_KEYS, where)
        name = str(cd.get("name", f"constraint{k}"))
        if name in names:
            raise ModelError(f"{where}.name: {name!r} is already used")
        names.add(name)
        kind = cd.get("type")
        if kind not in CONSTRAINT_TYPES:
            raise ModelError(f"{where}.type: expected one of {list(CONSTRAINT_TYPES)}, got {kind!r}")
        fa = cd.get("frame")
        if fa not in frames:
            raise ModelError(f"{where}.frame: {fa!r} is not a frame of this robot; frames: {sorted(frames)}")
        to = cd.get("to", "world")
        if to != "world" and to not in frames:
            raise ModelError(f"{where}.to: {to!r} is not 'world' or a frame; frames: {sorted(frames)}")
        if to == fa:
            raise ModelError(f"{where}.to: a frame cannot be constrained to itself")
        direction = np.array([0.0, 0.0, 1.0])
        if kind in ("line", "plane"):
            key = "direction" if kind == "line" else "normal"
            if to != "world":
                raise ModelError(f"{where}.to: {kind} constraints are to the world only")
            direction = _vec(cd, key, 3, where)
            nrm = np.linalg.norm(direction)
            if not nrm > 0:
                raise ModelError(f"{where}.{key}: expected a non-zero 3-vector")
            direction = direction / nrm
        target = None
        if "target" in cd:
            if to != "world":
                raise ModelError(f"{where}.target: only constraints to the world take a target pose")
            target = pose_from_dict(cd["target"], where + ".target")
        out.append(Constraint(name, kind, frames[fa], PointRef(-1) if to == "world" else frames[to],
                              target, direction))
    return out


def _with_targets(tree, constraints):
    """Constraints to the world without a target pose hold their frame where
    it is in the reference configuration q0."""
    from dataclasses import replace
    ws = None
    out = []
    for c in constraints:
        if c.b.joint < 0 and c.target is None:
            ws = Workspace(tree) if ws is None else ws
            g = np.eye(4) if c.a.joint < 0 else alg.point_poses(tree, ws, tree.q0, [c.a.joint], [c.a.x])[0]
            c = replace(c, target=g.copy())
        out.append(c)
    return out


def from_robot_model(robot, d=None, base_dir=None):
    """The mechanism of a classic robot description: the soft chain
    (:func:`soft_chain.robot_tree`), one member "backbone", no rigid
    joints, no constraints. ``d``: its mapping, for the stress geometry
    and the obstacles (mesh files relative to ``base_dir``).
    Without ``d`` the mechanism is made once per description (both are
    immutable) and kept with it."""
    if d is None:
        mech = robot.__dict__.get("_mechanism")
        if mech is None:
            mech = from_robot_model(robot, {})
            object.__setattr__(robot, "_mechanism", mech)
        return mech
    tree, owners, bases = robot.chain
    geo = [None] * len(robot.sections)
    if d.get("segments"):
        geo = _member_geometry(d["segments"], robot)
    p = tree.paths[0]
    member = Member("backbone", 0, p.joints, tuple(geo[o] for o in owners),
                    tuple(robot.sections[o].segment for o in owners))
    frames = {"tip": PointRef(p.joints[-1], tree.joints[p.joints[-1]].section.length)}
    mech = Mechanism(tree.name, tree, ("",) * tree.n_joints, (), (member,), (), frames, "fixed",
                     base_pose=np.array(robot.base_pose, dtype=float),
                     strain_bases=bases,
                     **_contact_fields(d, tree, (member,), base_dir))
    return mech


def with_strain_basis(mech, member, basis):
    """The mechanism with every section of soft member ``member`` on one
    strain basis along the whole member (any object with the methods of
    :class:`strain_bases.StrainBasis`, e.g. a
    :class:`strain_bases.CustomBasis` of a Python callable), replacing the
    bases its segments had. ModelError naming the member when it is not
    one, when its sections differ in their free modes, or when the basis
    does not fit its sections (checked here, at the door)."""
    try:
        m = mech.member(member)
    except KeyError as e:
        raise ModelError(f"member: {e.args[0]}") from None
    modes = [tuple(mech.tree.joints[j].section.modes) for j in m.joints]
    if len(set(modes)) != 1:
        raise ModelError(f"member {member!r}: its sections must share their free modes for one basis along it "
                         f"(they have {sorted(set(modes))})")
    bases = tuple(sb for sb in mech.strain_bases if sb.member != member) + (
        SegmentBasis(member, "member", tuple(m.joints), basis),)
    out = replace(mech, strain_bases=bases)
    robot_basis(out.tree, bases)           # the basis checked now (its values, its rank on the sections)
    return out


def _contact_fields(d, tree, members, base_dir=None):
    """The ``obstacles`` and ``contact`` of a robot mapping, checked: the
    world's obstacles (mesh files relative to ``base_dir``), the contact
    spacing and the capsules of the members that touch (``contact.between``;
    a classic rod's one member, "backbone", touches itself only)."""
    contact = d.get("contact") if isinstance(d.get("contact"), dict) else {}
    between = member_contact(contact.get("between"), [m.name for m in members])
    return dict(obstacles=obstacles_from_list(d.get("obstacles"), base_dir=base_dir),
                contact_spacing=contact_spacing(d.get("contact")),
                member_shapes=member_capsules(tree, members, *between) if between else ())


def shape_command(r, v, target, vmax, amax, h):
    """One step h of a position reference (r, v) towards ``target`` within
    |v| <= vmax and |a| <= amax: the velocity goes towards the fastest one
    that can still stop at the target (sqrt(2 amax |error|), at most vmax),
    changing by at most amax h; the last bit snaps onto the target. Returns
    the new (r, v). A stream of commands that respects the bounds is
    followed without lag; a jump becomes a smooth trapezoidal move."""
    err = target - r
    if abs(err) <= 0.5 * amax * h * h and abs(v) <= amax * h:
        return target, 0.0
    # braking distance of a discrete step: stop in time with the step's own acceleration
    v_des = np.sign(err) * min(vmax, np.sqrt(2.0 * amax * abs(err)) - 0.5 * amax * h)
    if np.sign(v_des) != np.sign(err):
        v_des = 0.0
    v_new = v + np.clip(v_des - v, -amax * h, amax * h)
    r_new = r + v_new * h
    if (target - r_new) * err <= 0:         # reached (or would overshoot): land on the target at rest
        return target, 0.0
    return r_new, v_new
