"""The digital twin of any robot, free of ROS (the node wraps it): a
classic rod is a one-member mechanism. :class:`Twin` is the state machine
the node drives (inputs, :meth:`Twin.step`, :meth:`Twin.outputs`,
``reset``, ``change_settings``, ``warm_up``) on the multibody engine with
joints and constraints (:mod:`soft_twin_core.solve.constrained`; the compiled O(n)
integrator and static Newton when the robot has no constraint rows):
``dynamic`` mode steps a
:class:`~soft_twin_core.solve.constrained.MechanismSimulator`, ``quasi_static``
mode solves the equilibrium on every input change, warm-started from the
last shape. It takes actuation, a tip wrench and joint commands (positions
of position-controlled joints, whose efforts are outputs, and efforts of
effort-controlled joints), checked at the door (:mod:`soft_twin_core.commands`).

Its :class:`Snapshot` carries everything the node publishes: the poses of
one forward pass at once, the loads inside the robot on first use.

A step that fails (no convergence, or the core raising on absurd numbers)
keeps the last good state and drops the input that broke it
(:class:`DropPolicy`; :attr:`UpdateInfo.dropped` says which), so the next
step runs with inputs that worked. The simulator is configured so that a
failing step costs about a millisecond (:class:`TwinSettings`: bounded
sub-stepping, no dense-Newton fallback).

Frames: "world" of the core model = the node's base frame. Wrenches are
[force (N); moment (N m)]. Not thread-safe: the node serialises calls.
"""

import contextlib
from dataclasses import dataclass, field
from functools import cached_property
import time

import numpy as np

from soft_twin_core._blas import one_blas_thread
from soft_twin_core.engine.algorithms import point_poses
from soft_twin_core.engine.workspace import Workspace
from soft_twin_core.errors import StaticsError
from soft_twin_core.planning import planner as pl
from soft_twin_core.planning.ik import frame_ik
from soft_twin_core.robot.mechanism import base_targets, shape_command, tip_frame
from soft_twin_core.robot.model import State
from soft_twin_core.robot.obstacles import check_unique_names
from soft_twin_core.solve import constrained as cs
from soft_twin_core.solve.contact import MemberContact
from soft_twin_core.solve.outputs import (main_member, q_from_section_strains, section_rates, section_strains,
                                          state_outputs, state_shape)
from soft_twin_core.text import clip

MODES = ("dynamic", "quasi_static")

# what a failing step may raise on absurd (finite) numbers: a failure, not a bug
STEP_ERRORS = (ArithmeticError, ValueError, np.linalg.LinAlgError, StaticsError)


@dataclass
class UpdateInfo:
    """Outcome of one :meth:`Twin.step`: steps taken, Newton iterations,
    converged (False: the state was kept), message, compute time [s];
    dropped: the inputs dropped because the step or solve failed with them,
    a tuple of "actuation" and/or "wrench" (they went back to those of the
    last good state)."""
    steps: int = 0
    iterations: int = 0
    converged: bool = True
    message: str = ""
    compute_time: float = 0.0
    stable: bool = True
    dropped: tuple = ()
    residual: float = None      # quasi-static: the equilibrium's force residual


@dataclass
class TwinSettings:
    """mode: "dynamic" | "quasi_static"; dt: dynamic step [s];
    theta: integrator theta in [0.5, 1]; tolerance: integrator Newton
    tolerance; points_per_section: backbone samples per section.

    The work a failing dynamic step may do (real time: it must fit in a step
    period): Newton iterations per attempt (``max_iterations``), sub-step
    halvings (``max_substep_levels``: a step may split into 2**levels
    pieces) and the core's dense full-Newton fallback (``full_newton``,
    off: it costs 25-700 ms a step on the 18-dof default arm). With these
    defaults a failing step costs about a millisecond (0.7-0.9 ms for the
    default arm, 1.4-1.6 ms for the 36-dof pneumatic arm; it was 25-200 ms
    with the core's defaults, 4 levels and the fallback), and a jump from
    rest to a 100 N tendon tension (default arm, theta 0.5) still
    integrates."""
    mode: str = "dynamic"
    dt: float = 0.005
    theta: float = 0.5
    tolerance: float = 1e-4
    points_per_section: int = 10
    max_iterations: int = 10
    max_substep_levels: int = 3
    full_newton: bool = False


class DropPolicy:
    """What a twin falls back to after a failed step or solve, for every
    robot: back to the inputs of the last good state if they changed since
    (those failed); else, once, to the inputs before the state's own (a
    late failure: the state's inputs stepped well for a while); with
    nothing left to drop, new inputs are not blamed: they are kept and tried
    at every step until one converges (or a reset). ``same(a, b)``: two
    input records alike."""

    def __init__(self, same, inputs):
        self.same = same
        self.reset(inputs)

    def reset(self, inputs):
        self.good, self.fallback, self.stuck = inputs, None, False

    def succeeded(self, inputs):
        """A step or solve succeeded with ``inputs``: they are the good ones."""
        if not self.same(inputs, self.good):
            self.fallback = self.good
        self.good, self.stuck = inputs, False

    def target(self, now):
        """The inputs to go back to after a failure with ``now`` (None: keep them)."""
        if self.stuck:
            return None
        if not self.same(now, self.good):
            return self.good
        if self.fallback is not None and not self.same(now, self.fallback):
            self.good, self.fallback = self.fallback, None
            return self.good
        self.stuck = True
        return None


def _same_inputs(a, b):
    """Two input tuples of :meth:`Twin._inputs_tuple` alike (the
    stamps by identity)."""
    return (np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2] and a[3] == b[3]
            and a[4] == b[4] and all(x is y for x, y in zip(a[5:8], b[5:8])) and a[8] == b[8]
            and _same_pose(a[9], b[9]))


def _same_pose(a, b):
    """Two commanded base poses alike (None: the robot file's)."""
    return (a is None) == (b is None) and (a is None or np.array_equal(a, b))


@dataclass
class TwinIK:
    """An IK answer: ``names`` the robot's position-controlled joints, then
    its actuators; ``values`` their commands (rad or m, then N or Pa) whose
    equilibrium ``q`` puts the tip at ``achieved_pose`` (4x4, world);
    ``status`` as the planner's (``reached``, ``at_limit``, ``rate_limit``,
    ``out_of_workspace``, ``statics_failed``; ``shape_only``: a robot without
    inputs, ``q`` the shape reaching the target, ``actuation_found``
    False); ``strains`` (n_soft_sections, 6); ``orientation_error`` [rad]
    (0 for a position target)."""
    reached: bool
    status: str
    names: tuple
    values: np.ndarray
    q: np.ndarray
    strains: np.ndarray
    achieved_pose: np.ndarray
    position_error: float
    iterations: int
    orientation_error: float = 0.0
    actuation_found: bool = True          # False: a shape only (a robot without inputs)


@dataclass(frozen=True)
class Snapshot:
    """One state: mode, t [s], u (actuation), joint names and positions,
    velocities, efforts (rad, rad/s, N m or m, m/s, N); backbones {member:
    (poses (N, 4, 4), s (N,))} at the settings' points per section; main
    member name; backbone and s of the main member (the one with the tip),
    tip_pose; strains and strain_rates (n_soft_sections, 6) in tree order;
    frames {name: 4x4}; tip_wrench (the load at the tip frame, tip axes);
    point_loads (the other points' loads: (point, position, force), world);
    command_stamp. These come from one forward pass (the poses), what every
    published state needs. The loads inside the robot are computed on
    first use, once (an RNEA pass and the members' cut wrenches; the node
    asks for them at ``wrench_rate_hz``): ``base_wrench`` (the support's
    reaction on the robot: the sum of the root joints' transmitted wrenches,
    base axes, about the base origin), ``constraint_wrenches`` {name: world
    [f; m] on its frame}, ``joint_wrenches`` {rigid joint: world [f; m]
    transmitted through it (the parent side on the child side), about the
    joint's origin}, ``internal_wrenches`` {member: (N, 6) at its backbone
    points, section axes} and ``stresses`` {member: (peak normal, peak
    shear) Pa}."""
    mode: str
    t: float
    u: np.ndarray
    joint_names: tuple
    joint_positions: np.ndarray
    joint_velocities: np.ndarray
    joint_efforts: np.ndarray
    backbones: dict
    main_member: str
    s: np.ndarray
    backbone: np.ndarray
    tip_pose: np.ndarray
    strains: np.ndarray
    strain_rates: np.ndarray
    frames: dict
    tip_wrench: np.ndarray
    command_stamp: object = None
    points_per_section: int = 1     # backbone points per section (every member's section boundaries: [::pps])
    contacts: object = None         # robots with obstacles: the engine.contact.ContactState of this state
    obstacles: tuple = ()           # the obstacles of this state (those ``contacts`` index)
    state: tuple = field(default=None, repr=False)    # (mech, q, v, a, lam, inputs): what the loads need
    point_loads: tuple = ()         # the point wrenches: (point, position (3,) [m], force (3,) [N], world)

    @cached_property
    def _loads(self):
        mech, q, v, a, lam, inp = self.state
        return state_outputs(mech, q, lam, inp, v, a, points_per_section=self.points_per_section,
                             member_motion=False, contacts=self.contacts)

    @property
    def base_wrench(self):
        return self._loads.base_wrench

    @property
    def constraint_wrenches(self):
        return self._loads.constraint_wrenches

    @property
    def joint_wrenches(self):
        return {n: self._loads.joint_wrenches[n] for n in self.joint_names}

    @property
    def internal_wrenches(self):
        return {m.name: m.internal_wrench for m in self._loads.members}

    @property
    def stresses(self):
        return {m.name: (float(np.nanmax(m.normal_stress, initial=0.0)), float(np.nanmax(m.shear_stress, initial=0.0)))
                for m in self._loads.members}


def _ik_error(r, with_rot):
    """An IK answer's distance from its target: position [m] plus 0.1 m/rad
    of orientation when it has one (the solver's weighting)."""
    return r.position_error + (0.1 * r.orientation_error if with_rot else 0.0)


class Twin:
    """A mechanism, its state and inputs (see the module docstring). Not
    thread-safe: the node serialises calls."""

    def __init__(self, mech, settings=None, obstacles=None):
        """``obstacles``: what the members touch (default the robot file's)."""
        self.mech = mech
        self.model = mech            # what the node reads: name, actuators, actuator_names
        self.settings = settings or TwinSettings()
        self.tip = tip_frame(mech)
        self.u = np.zeros(len(mech.actuators))
        self.tip_wrench = np.zeros(6)
        self.tip_frame = "world"
        self.point_wrenches = {}         # {point: (wrench (6,), "world" | "body")}: loads on other points
        self.positions = {mech.tree.joints[i].name: mech.tree.joints[i].q_ref for i in mech.joints_with("position")}
        self.efforts = {mech.tree.joints[i].name: 0.0 for i in mech.joints_with("effort")}
        self.base_pose = None            # a prescribed base's commanded pose (4x4; None: the robot file's)
        self.command_stamp = None
        self.joint_stamp = None          # the newest joint command's header
        self.actuation_stamp = None      # the newest actuation command's header
        self._dirty = True
        self._version = 0                # counts the changes of the inputs (core_inputs' cache, _commit)
        self._core = (None, None)        # (version, Inputs) of the commands as they are
        self._tangent = None             # the last equilibrium's tangent (robots without multipliers): a hint
        self.obstacles = check_unique_names(tuple(mech.obstacles if obstacles is None else obstacles),
                                            "obstacles")       # what the members touch now (set_obstacles)
        self._moved = None               # dynamic: obstacles moved, where the next step takes them
        self._stick = None               # quasi-static friction: where the contact points stick (_sticking)
        self._contact = None             # (obstacles, MemberContact) of the stick points
        self._rest_of = self.obstacles   # the obstacles the rest shape was solved with
        self.rest_q, self.rest_message, self.rest_contacts = self._rest()
        self.lam = np.zeros(mech.n_constraint_rows + len(mech.joints_with("position")))
        self._keep_good(reset=True)
        self.reset(solve=False)

    # --- inputs -------------------------------------------------------------
    def _keep_good(self, reset=False):
        """The current inputs are those of a good state (a step or solve
        succeeded with them): what a failed one falls back to; the good
        inputs before them are kept as the fallback of a late failure."""
        now = self._inputs_tuple()
        if reset:
            self._policy = DropPolicy(_same_inputs, now)
        else:
            self._policy.succeeded(now)
        self._good = now
        self._good_version = self._version
        self._good_joint_stamp = self.joint_stamp
        self._good_actuation_stamp = self.actuation_stamp

    def _inputs_tuple(self):
        return (self.u.copy(), self.tip_wrench.copy(), self.tip_frame, dict(self.positions), dict(self.efforts),
                self.command_stamp, self.joint_stamp, self.actuation_stamp, self._points_tuple(),
                None if self.base_pose is None else self.base_pose.copy())

    def _points_tuple(self):
        """The point wrenches as plain, comparable data."""
        return tuple(sorted((p, tuple(float(x) for x in w), axes) for p, (w, axes) in self.point_wrenches.items()))

    def core_inputs(self, positions=None, velocities=None):
        """The core Inputs of the current commands (``positions``,
        ``velocities``: instead of the commanded ones, e.g. the shaped
        references), assembled without a second check: the node checked
        every command at the door (:func:`parse_joint_command`,
        :func:`soft_twin_core.commands.parse_actuation`, :func:`soft_twin_core.commands.parse_tip_wrench`).
        The commands' own Inputs are kept until they change (a step at 200 Hz
        must not assemble the same inputs again)."""
        if positions is None and velocities is None:
            version, inp = self._core
            if version == self._version:
                return inp
        inp = cs.assemble_inputs(self.mech, self.u, self.efforts,
                                 self.positions if positions is None else positions, velocities, self.held_loads())
        if positions is None and velocities is None:
            self._core = (self._version, inp)
        return inp

    def _changed(self):
        """The inputs changed: a quasi-static twin solves again, the cached
        Inputs go."""
        self._version += 1
        self._dirty = True

    def _shaped(self, h):
        """The position references after one step h towards the commands
        (:func:`mechanism.shape_command`, the joints' max_velocity and
        max_acceleration): new {joint: (r, v)}."""
        out = {}
        for name, (r, v) in self._ref.items():
            vmax, amax = self.mech.motion_limits.get(name, (np.inf, np.inf))
            out[name] = shape_command(r, v, self.positions[name], vmax, amax, h)
        return out

    def set_actuation(self, u, stamp=None):
        self.u = np.array(u, dtype=float)
        self.command_stamp = self.actuation_stamp = stamp
        self._changed()

    def set_tip_wrench(self, wrench, frame="world"):
        self.tip_wrench, self.tip_frame = np.array(wrench, dtype=float), frame
        self._changed()

    def set_point_wrench(self, point, wrench, axes="world"):
        """A wrench [f; m] (N, N m) on ``point`` (a frame of the robot or
        ``"<member>@<s>"``, checked at the door:
        :func:`soft_twin_core.commands.parse_point_wrench`), in ``axes``
        "world" (a dead load) or "body" (the point's); it replaces the one
        before on that point, and all zeros removes it."""
        w = np.array(wrench, dtype=float)
        if np.any(w):
            self.point_wrenches[str(point)] = (w, axes)
        else:
            self.point_wrenches.pop(str(point), None)
        self._changed()

    def set_joint_commands(self, positions, efforts, stamp=None):
        self.positions, self.efforts = dict(positions), dict(efforts)
        self.command_stamp = stamp if stamp is not None else self.command_stamp
        self.joint_stamp = stamp
        self._changed()

    def set_base_pose(self, pose):
        """Where a prescribed base is carried to (4x4 in the robot file's
        world, checked at the door: :func:`soft_twin_core.commands.parse_base_pose`):
        the next dynamic step moves it there (a clamp of the base frame to a
        moving target; the pose commanded before is where the step starts,
        so a stream should start at the base's pose, and a jump is a jolt
        the step may refuse: then it is dropped); the next solve holds it
        there. None: back to the robot file's pose."""
        self.base_pose = None if pose is None else np.array(pose, dtype=float)
        self._changed()

    def _targets(self):
        """The constraints' world targets for the simulator: the prescribed
        base's commanded pose (None: every constraint's own)."""
        return base_targets(self.mech, self.base_pose)

    @property
    def joint_command_pending(self):
        """A joint command applied that no step or solve has used yet."""
        return self.joint_stamp is not None and self.joint_stamp is not self._good_joint_stamp

    @property
    def command_pending(self):
        """An actuation command applied that no step or solve has used yet."""
        return self.actuation_stamp is not None and self.actuation_stamp is not self._good_actuation_stamp

    @property
    def needs_solve(self):
        return self.settings.mode == "quasi_static" and self._dirty

    # --- state --------------------------------------------------------------
    def _rest(self):
        """Equilibrium under gravity with the joints at their references
        (statics; what touches an obstacle or a shape with friction where
        the robot file places it sticks there: a loose object on a table;
        a robot with a floating base, or a loose object nothing holds,
        starts from its reference configuration). Returns (q, message, its
        contacts)."""
        try:
            mc = self._member_contact()
            stick = mc.stuck_at(Workspace(self.mech.tree), self.mech.tree.q0) if mc.has_friction else None
            eq = cs.solve_equilibrium(self.mech, obstacles=self.obstacles, stick=stick)
            return eq.q.copy(), "rest: static equilibrium under gravity", eq.contacts
        except (ValueError, cs.StaticsError) as e:
            return self.mech.tree.q0.copy(), f"rest: reference configuration ({clip(e, 200)})", None

    def _new_sim(self, q, v):
        s = self.settings
        # the work a failing step may do is bounded as the settings say (real time: see TwinSettings)
        return cs.MechanismSimulator(self.mech, s.dt, s.theta, q, v, tol=s.tolerance,
                                     max_iterations=max(s.max_iterations, 10),
                                     max_substep_levels=s.max_substep_levels, full_newton=bool(s.full_newton),
                                     obstacles=self.obstacles, carried_secant=True)    # streamed base poses

    def _sim_at_state(self):
        """A new simulator at the twin's state (q, v, t, multipliers): after
        the set of obstacles changed."""
        sim = self._new_sim(self.state.q, self.state.qdot)
        sim.t = self.state.t
        sim.lam = self.lam.copy()
        return sim

    def set_obstacles(self, obstacles):
        """What the members touch from now on (engine.contact.Obstacle,
        each checked at the door: :mod:`soft_twin_core.robot.obstacles`;
        ModelError for repeated names).
        The same obstacles (names and kinds, in order) at new poses move
        there over the next dynamic step: the contacts see their velocity.
        Any other change takes effect at once (the simulator is remade at the
        current state). Quasi-static: the next solve has them. A reset
        solves the rest shape again with them."""
        obstacles = check_unique_names(tuple(obstacles), "obstacles")
        self._stick = None               # stick points on the obstacles as they were: made again
        same = (len(obstacles) == len(self.obstacles) and all(
            a.name == b.name and a.kind == b.kind for a, b in zip(obstacles, self.obstacles)))
        if self._sim is not None and same and obstacles and self._sim.contact:
            self._moved = obstacles
            return
        self.obstacles, self._moved = obstacles, None
        if self._sim is not None:
            self._sim = self._sim_at_state()
        self._dirty = self.settings.mode == "quasi_static"

    def reset(self, solve=True):
        mech = self.mech
        if self._moved is not None:
            self.obstacles, self._moved = self._moved, None
        if self._rest_of is not self.obstacles:
            self._rest_of = self.obstacles
            self.rest_q, self.rest_message, self.rest_contacts = self._rest()
        self.u = np.zeros(len(mech.actuators))
        self.tip_wrench, self.tip_frame = np.zeros(6), "world"
        self.point_wrenches = {}
        self.base_pose = None
        self.positions = {mech.tree.joints[i].name: mech.tree.joints[i].q_ref for i in mech.joints_with("position")}
        self.efforts = {mech.tree.joints[i].name: 0.0 for i in mech.joints_with("effort")}
        self.command_stamp = self.joint_stamp = self.actuation_stamp = None
        self._version += 1
        self._keep_good(reset=True)
        self.state = State(self.rest_q.copy(), np.zeros(mech.tree.nv), 0.0)
        self._ref = {n: (float(v), 0.0) for n, v in self.positions.items()}
        self.lam = np.zeros_like(self.lam)
        self.contacts = self.rest_contacts
        self._stick = None
        self._sim = self._new_sim(self.state.q, self.state.qdot) if self.settings.mode == "dynamic" else None
        if self._sim is not None:
            self._sim.start_multipliers(self.core_inputs())
            self.lam = self._sim.lam.copy()
        self._dirty = self.settings.mode == "quasi_static"
        if solve and self._dirty:
            self._solve()

    def change_settings(self, settings):
        if settings.mode not in ("dynamic", "quasi_static"):
            raise ValueError(f"mode: expected dynamic or quasi_static, got {settings.mode!r}")
        old, self.settings = self.settings, settings
        if (settings.mode, settings.dt, settings.theta, settings.tolerance) != \
                (old.mode, old.dt, old.theta, old.tolerance):
            v = self.state.qdot if settings.mode == old.mode else np.zeros(self.mech.tree.nv)
            self.state = State(self.state.q.copy(), v.copy(), self.state.t)
            self._sim = self._new_sim(self.state.q, self.state.qdot) if settings.mode == "dynamic" else None
            if self._sim is not None:
                self._sim.t = self.state.t
            tree = self.mech.tree
            self._ref = {n: (float(self.state.q[tree.idx_q[tree.joint_index(n)]]), 0.0) for n in self.positions}
            self._dirty = True
            self._stick = None

    def warm_up(self):
        """One throw-away step and solve (numba's kernels load or compile)."""
        t0 = time.perf_counter()
        sim = self._new_sim(self.state.q, self.state.qdot)
        try:
            sim.step(inputs=self.core_inputs())
        except (cs.StepError,) + STEP_ERRORS:
            pass            # the kernels ran; the twin's own first step reports a failure itself
        self.outputs()
        return time.perf_counter() - t0

    # --- advancing ----------------------------------------------------------
    def step(self, n=1):
        """Dynamic: up to n steps of dt. Quasi-static: one equilibrium solve
        for the current inputs (if they changed). On failure the state is
        kept (the last good one), ``converged`` is False, the remaining
        steps are not tried, and the input that failed is dropped
        (:class:`soft_twin_core.twin.DropPolicy`)."""
        t0 = time.perf_counter()
        if self.settings.mode != "dynamic":
            if self._moved is not None:
                self.obstacles, self._moved = self._moved, None
                self._dirty = True
            info = self._solve()
            info.compute_time = time.perf_counter() - t0
            return info
        info = UpdateInfo()
        shaping = bool(self._ref)          # position-controlled joints follow shaped references
        inp = None if shaping else self.core_inputs()      # else the inputs hold over the n steps
        with one_blas_thread() if self.lam.size else contextlib.nullcontext():   # dense KKT solves only
            for _ in range(n):
                if shaping:
                    ref = self._shaped(self.settings.dt)
                    inp = self.core_inputs({k: r for k, (r, _) in ref.items()}, {k: v for k, (_, v) in ref.items()})
                try:
                    self._sim.step(inputs=inp, targets=self._targets(), obstacles=self._moved)
                    if self._moved is not None:
                        self.obstacles, self._moved = self._moved, None
                except (cs.StepError,) + STEP_ERRORS as e:
                    if info.steps:
                        self._commit()
                    info.converged = False
                    info.dropped = self._drop()
                    if self._moved is not None:      # the move is dropped too: the obstacles stay put
                        self._moved = None
                        self._sim = self._sim_at_state()
                        info.dropped += ("obstacles",)
                    why = clip(e, 300) if isinstance(e, cs.StepError) else f"{type(e).__name__}: {clip(e, 300)}"
                    info.message = (f"dynamics step at t = {self.state.t:.4f} s did not converge ({why}); "
                                    f"state kept at the last good step"
                                    + (f", input dropped ({' and '.join(info.dropped)})" if info.dropped else ""))
                    break
                info.steps += 1
                if shaping:
                    self._ref = ref
                info.iterations += self._sim.iterations
            else:
                if info.steps:
                    self._commit()
        info.compute_time = time.perf_counter() - t0
        return info

    def _commit(self):
        """The simulator's state is the twin's, reached with the current inputs."""
        self.state = State(self._sim.q.copy(), self._sim.v.copy(), self._sim.t)
        self.lam = self._sim.lam.copy()
        self.contacts = self._sim.contacts
        if self._version != self._good_version:
            self._keep_good()
        else:                             # the good inputs stepped again (DropPolicy.succeeded, without the compare)
            self._policy.stuck = False

    def _drop(self):
        """After a failed step or solve: :class:`soft_twin_core.twin.DropPolicy`
        (the rod twin's too) says what to go back to. Returns what was dropped."""
        now = self._inputs_tuple()
        target = self._policy.target(now)
        if target is None:
            return ()
        self._good = target
        dropped = []
        if not np.array_equal(now[0], target[0]) or now[7] is not target[7]:
            dropped.append("actuation")
        if now[3] != target[3] or now[4] != target[4] or now[6] is not target[6]:
            dropped.append("joint")
        if not np.array_equal(now[1], target[1]) or now[2] != target[2] or now[8] != target[8]:
            dropped.append("wrench")
        if not _same_pose(now[9], target[9]):
            dropped.append("base_pose")
        (u, w, frame, pos, eff, self.command_stamp, self.joint_stamp, self.actuation_stamp, points,
         self.base_pose) = target
        self.point_wrenches = {p: (np.array(w_), axes) for p, w_, axes in points}
        self._good_joint_stamp, self._good_actuation_stamp = self.joint_stamp, self.actuation_stamp
        self.u, self.tip_wrench, self.tip_frame = u.copy(), w.copy(), frame
        self.positions, self.efforts = dict(pos), dict(eff)
        self._version += 1
        # the simulator's state is unchanged by a failed step
        return tuple(dropped)

    def _member_contact(self):
        """The MemberContact of the current obstacles (made once for them)."""
        if self._contact is None or self._contact[0] is not self.obstacles:
            self._contact = (self.obstacles, MemberContact(self.mech, self.obstacles))
        return self._contact[1]

    def _sticking(self):
        """Where the contact points stick (:class:`solve.contact.StickPoints`)
        for the friction of the next solve: kept from solve to solve (statics
        with friction has a history: a load that slid the arm and is taken
        off leaves it where friction holds it), made at the current state
        when there are none (after a reset, a change of obstacles or of
        mode: the points touching then stick where they are); None when no
        obstacle and no body's shape has friction."""
        mc = self._member_contact()
        if not mc.has_friction:
            return None
        if self._stick is None:
            ws = Workspace(self.mech.tree)
            self._stick = mc.stuck_after(ws, self.state.q, mc.stick_points(ws, self.state.q), self.contacts)
        return self._stick

    def _solve(self):
        if not self._dirty:
            return UpdateInfo()
        self._dirty = False
        try:
            stick = self._sticking()
            eq = cs.solve_equilibrium(self.mech, q_init=self.state.q, inputs=self.core_inputs(),
                                      tangent_hint=self._tangent, obstacles=self.obstacles, targets=self._targets(),
                                      stick=stick)
        except (ValueError, cs.StaticsError) + STEP_ERRORS as e:
            dropped = self._drop()
            return UpdateInfo(0, 0, False, f"statics failed for the last input (dropped): {clip(e, 300)}; "
                                           f"state kept", dropped=dropped)
        self._keep_good()
        self._tangent = eq.tangent
        residual = eq.residual
        self._ref = {n: (float(v), 0.0) for n, v in self.positions.items()}
        self.state.q = eq.q.copy()
        self.state.qdot = np.zeros(self.mech.tree.nv)
        self.lam = eq.lam.copy()
        self.contacts = eq.contacts
        if stick is not None:
            self._stick = self._member_contact().stuck_after(Workspace(self.mech.tree), eq.q, stick, eq.contacts)
        return UpdateInfo(1, eq.iterations, True, "" if eq.stable else
                          f"only an unstable equilibrium was found (smallest reduced stiffness eigenvalue "
                          f"{eq.min_stiffness_eigenvalue:.3g}): the robot buckles or snaps through under these "
                          f"inputs", stable=eq.stable, residual=float(residual))

    # --- queries (never touch this twin) ------------------------------------
    def query_copy(self):
        """A quasi-static copy with this twin's commands and shape (cheap:
        the model is shared), for queries run outside the node's lock."""
        import copy
        q = copy.copy(self)
        q.settings = TwinSettings(mode="quasi_static", points_per_section=self.settings.points_per_section)
        q.state = State(self.state.q.copy(), np.zeros(self.mech.tree.nv), self.state.t)
        q.positions, q.efforts = dict(self.positions), dict(self.efforts)
        q.lam, q._sim = self.lam.copy(), None
        return q

    def query_state(self):
        """What a query needs of this twin, as plain data (for a query run
        in another process: :mod:`soft_twin.query_worker`)."""
        return dict(q=self.state.q.copy(), t=float(self.state.t), u=self.u.copy(),
                    tip_wrench=self.tip_wrench.copy(), tip_frame=self.tip_frame, positions=dict(self.positions),
                    efforts=dict(self.efforts), lam=self.lam.copy(), points=self._points_tuple(),
                    base_pose=None if self.base_pose is None else self.base_pose.copy(), stick=self._stick)

    def load_query_state(self, st):
        """Become the quasi-static query twin of :meth:`query_state` ``st``."""
        self.settings = TwinSettings(mode="quasi_static")
        self.state = State(st["q"].copy(), np.zeros(self.mech.tree.nv), st["t"])
        self.u, self.tip_wrench, self.tip_frame = st["u"].copy(), st["tip_wrench"].copy(), st["tip_frame"]
        self.point_wrenches = {p: (np.array(w), axes) for p, w, axes in st.get("points", ())}
        self.positions, self.efforts = dict(st["positions"]), dict(st["efforts"])
        self.base_pose = None if st.get("base_pose") is None else np.array(st["base_pose"])
        self._stick = st.get("stick")
        self.lam, self._sim = st["lam"].copy(), None
        self._changed()

    def statics(self, actuation, wrench, frame="world"):
        """(UpdateInfo, snapshot) of the equilibrium under these inputs,
        warm-started from the current shape (on a :meth:`query_copy`)."""
        self.set_actuation(actuation)
        self.set_tip_wrench(wrench, frame)
        info = self._solve()
        return info, (self.outputs() if info.converged else None)

    def forward_kinematics(self, strains=(), actuation=None):
        """(message, snapshot) of a shape, the twin untouched (on a
        :meth:`query_copy`): the given section strains ((n_soft_sections x 6)
        values in tree order, the joints where they are now), or the
        equilibrium under ``actuation`` (inputs vector; gravity, the current
        joint commands, no tip wrench), or (neither) the current state.
        Raises ValueError (ModelError) naming a bad input, StaticsError."""
        strains = np.asarray(list(strains), dtype=float)
        if strains.size and actuation is not None:
            raise ValueError("give strains or an actuation, not both")
        if strains.size:
            self.state.q = q_from_section_strains(self.mech, strains, self.state.q)
            message = "ok: shape of the given strains (joints at their current positions)"
            if self.mech.n_constraint_rows:
                # a closed chain: strains alone need not close it (the passive joints follow from the closure)
                phi, _ = cs.constraint_rows(self.mech, Workspace(self.mech.tree), self.state.q)
                gap = float(np.abs(phi[:self.mech.n_constraint_rows]).max(initial=0.0))
                message += f"; the constraints are violated by up to {gap:.3g} m or rad with them" if gap > 1e-9 \
                    else "; the constraints hold"
            return message, self.outputs()
        if actuation is not None:
            info, snap = self.statics(actuation, np.zeros(6))
            if not info.converged:
                raise cs.StaticsError(info.message)
            return "ok: static shape under the actuation, the joint commands and gravity" + (
                "" if info.stable else " (unstable equilibrium)"), snap
        return "ok: the twin's current shape", self.outputs()

    def held_loads(self):
        """The tip wrench and the point wrenches as the core's point loads
        (empty without any)."""
        return self._loads_of(self.tip_wrench, self.tip_frame, self._points_tuple())

    def _point_loads_out(self, ws, q, points):
        """(point, position [m], force [N]) in the world of each point wrench at q."""
        if not points:
            return ()
        refs = [self.mech.frame(p) for p, _, _ in points]
        poses = point_poses(self.mech.tree, ws, q, [r.joint for r in refs], [r.x for r in refs])
        return tuple((p, T[:3, 3].copy(), (T[:3, :3] @ np.array(w[:3])) if axes == "body" else np.array(w[:3]))
                     for (p, w, axes), T in zip(points, poses))

    def _loads_of(self, w, frame, points):
        """FrameLoads of a tip wrench (``frame`` "world" or "body") and of
        :meth:`_points_tuple` entries."""
        out = [cs.FrameLoad(self.tip, w, "world" if frame == "world" else "body")] if np.any(w) else []
        return out + [cs.FrameLoad(p, np.array(pw), axes) for p, pw, axes in points]

    def plan_options(self, **kw):
        """Planner options for this twin's tip frame, with its current joint
        efforts and tip wrench held and a prescribed base where it is now
        (``kw``: the other options)."""
        return pl.PlanOptions(frame=self.tip, efforts=dict(self.efforts),
                              point_loads=tuple(self.held_loads()), base_pose=self.base_pose, **kw)

    def command_vector(self, solver):
        """x = [position commands of ``solver.joint_names``, actuator inputs] now."""
        return np.concatenate([[self.positions[n] for n in solver.joint_names], self.u])

    def inverse_kinematics(self, target, tolerance=1e-6):
        """Joint commands and actuator inputs putting the tip at ``target``
        (base-frame position (3,) [m], or pose 4x4: then with the tip's
        orientation, weighted 0.1 m/rad; ``tolerance`` in m and rad), from
        the current commands and shape (the
        planner's sample solve, :class:`soft_twin_core.planning.planner.TipSolver`:
        joint limits, tensions in [0, limit], least change of the joint
        commands and least tension among redundant inputs; the current joint
        efforts and tip wrench held); a target it does not reach is tried
        again from rest, the closer answer kept. Raises PlanError,
        StaticsError or ValueError."""
        target = np.asarray(target, float)
        if not (self.mech.actuators or self.mech.joints_with("position")):
            # nothing drives this robot: the shape that would reach the target (not an equilibrium)
            r = frame_ik(self.mech, self.tip, target, self.state.q, position_only=target.shape == (3,),
                         tol_position=tolerance, tol_orientation=tolerance)
            return TwinIK(bool(r.success), "reached" if r.success else "shape_only", (), np.zeros(0), r.q.copy(),
                          section_strains(self.mech, r.q), r.achieved_pose, r.position_error, int(r.iterations),
                          0.0 if target.shape == (3,) else r.orientation_error, actuation_found=False)
        solver = pl.TipSolver(self.mech, self.plan_options(tolerance=tolerance, tolerance_rad=tolerance))
        solver.with_rot = target.shape == (4, 4)
        x0 = np.clip(self.command_vector(solver), solver.lower, solver.upper)
        r = solver.solve(target, x0, self.state.q)
        if not r.reached:
            # a second start at rest (the joints' reference commands, no actuation): from a state far off
            # (the tendon arm curled by 16 N and 18 N) the solve ended in a poor local optimum, 280 mm
            # from a target 40 mm above the rest tip, against the 32 mm the arm can come to from rest
            tree = self.mech.tree
            ref = {tree.joints[i].name: tree.joints[i].q_ref for i in self.mech.rigid_joints}
            x_ref = np.clip(np.concatenate([[ref[n] for n in solver.joint_names], np.zeros(len(self.u))]),
                            solver.lower, solver.upper)
            if not np.allclose(x_ref, x0):
                r_ref = solver.solve(target, x_ref, self.rest_q)
                if r_ref.reached or _ik_error(r_ref, solver.with_rot) < _ik_error(r, solver.with_rot):
                    r = r_ref
        return TwinIK(bool(r.reached), r.status, solver.joint_names + solver.actuator_names, r.x, r.q.copy(),
                      section_strains(self.mech, r.q), r.pose, r.position_error, int(r.iterations),
                      r.orientation_error)

    def plan(self, path, **options):
        """:func:`soft_twin_core.planning.planner.plan_path` from the current
        commands and shape, the tip frame following ``path`` (base frame),
        the current joint efforts and tip wrench held; with ``max_rate``,
        the rate limits hold from the current commands."""
        o = self.plan_options(**options)
        solver = pl.TipSolver(self.mech, o)
        # with a rate limit the plan starts from the current inputs (it cannot jump away from them)
        return pl.plan_path(self.mech, path, o, start=self.command_vector(solver), q_start=self.state.q,
                            solver=solver, from_start=o.max_rate is not None)

    # --- outputs ------------------------------------------------------------
    def outputs(self):
        """The :class:`Snapshot` of the current state, with the
        inputs it reflects (after a failed step or solve: those of the last
        good one): its poses now, the loads inside the robot on first use."""
        mech, tree = self.mech, self.mech.tree
        u, w, frame, pos, eff, stamp = self._good[:6]
        dynamic = self.settings.mode == "dynamic" and self._sim is not None
        q = self.state.q.copy()
        v = self.state.qdot.copy() if dynamic else None
        a = self._sim.a.copy() if dynamic else None
        if self._good_version == self._version:          # the good state's inputs are the commands'
            inp = self.core_inputs()
        else:                                             # (checked at the door)
            inp = cs.assemble_inputs(mech, u, eff, pos, None, self._loads_of(w, frame, self._good[8]))
        ws = self.__dict__.get("_shape_ws")
        if ws is None:
            ws = self._shape_ws = Workspace(tree)
        frames, backbones = state_shape(mech, ws, q, self.settings.points_per_section)
        names = mech.joint_names
        tip_pose = frames[self.tip]
        main = getattr(main_member(mech, self.tip), "name", "")
        bb, s = backbones.get(main, (tip_pose[None], np.zeros(1)))
        rates = section_rates(mech, v) if v is not None else np.zeros((len(tree.soft_joints), 6))
        R = tip_pose[:3, :3]
        tip_w = np.concatenate([R.T @ w[:3], R.T @ w[3:]]) if frame == "world" else w.copy()
        iq = [tree.idx_q[tree.joint_index(n)] for n in names]
        iv = [tree.idx_v[tree.joint_index(n)] for n in names]
        efforts = cs._efforts_out(mech, self.lam, inp)
        return Snapshot(point_loads=self._point_loads_out(ws, q, self._good[8]),
            mode=self.settings.mode, t=float(self.state.t), u=u.copy(), joint_names=names,
            joint_positions=q[iq].copy(), joint_velocities=v[iv].copy() if v is not None else np.zeros(len(names)),
            joint_efforts=np.array([efforts[n] for n in names]),
            backbones=backbones, main_member=main, s=s, backbone=bb, tip_pose=tip_pose,
            strains=section_strains(mech, q), strain_rates=rates, frames=frames, tip_wrench=tip_w,
            command_stamp=stamp, points_per_section=self.settings.points_per_section, contacts=self.contacts,
            obstacles=self.obstacles,
            state=(mech, q, v, a, self.lam.copy(), inp))
