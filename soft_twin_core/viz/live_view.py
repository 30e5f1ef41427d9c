"""A live 3D view of the twin in the browser (viser: a local web server and
its bundled three.js client; works offline). Shows the backbone as a tube
with the members' radii, rigid links as bars or, for articulated robots,
their visual shapes (boxes, cylinders, spheres) with the rigid joints as
dots and axis segments, the frames of the base and
the tip, the tip wrench as an arrow, and a panel with the time and the
actuation values.

    view = LiveView(port=8080)            # http://127.0.0.1:8080
    view.show(snapshot, radii=..., actuation={"tendon_y_pos": 2.0}, tip_force=[0, 0, -0.1])

Used by ``soft-twin-sim view`` (a recorded or simulated run played back in
a loop) and by the twin node (parameter ``live_view_port``). ``show`` is
cheap and thread-safe (viser sends the updates from its own thread).

The page can drive what it shows (issue 31): :meth:`LiveView.set_controls`
adds a slider per :class:`Control` (an actuator, a position- or
effort-controlled joint; range and unit in its label), pause, single
step, reset and a slow-motion slider; each calls back its owner (the
node sends them through its own input path and services).
"""

import collections
import threading
import time
from dataclasses import dataclass

import numpy as np

TUBE_SIDES = 16
TUBE_COLOR = (217, 115, 51)
LINK_COLOR = (70, 70, 70)
SHAPE_COLOR = (64, 96, 170)    # rigid links' visual shapes (articulated robots)
JOINT_COLOR = (20, 20, 20)
FORCE_COLOR = (204, 41, 204)
TRAIL_COLOR = (40, 150, 90)      # the tip's path
GHOST_COLOR = (140, 60, 230)     # an IK answer's shape, before it is applied (violet)
OBSTACLE_COLOR = (120, 120, 120)
CONTACT_COLOR = (204, 41, 204)   # contact forces, as the tip load
TENDON_COLOR = (0, 140, 150)     # the tendons' routes
GRID_COLOR = (205, 205, 205)    # the floor's grid
CHAMBER_COLOR = (50, 80, 220)    # the chambers' routes
TRAIL_SECONDS = 10.0             # the tip path drawn: the last 10 s
TRAIL_STEP_M = 0.001             # ... a point each time the tip has moved 1 mm
FOLLOW_HOLD_S = 1.0              # a slider the page moved follows the twin again after 1 s
# members coloured by a value: 0 -> blue, half -> light grey, the largest -> red (a diverging map, "coolwarm"'s
# ends: none of its colours is the plain tube's orange)
VALUE_COLORS = np.array([[59, 76, 192], [221, 221, 221], [180, 4, 38]], dtype=float)


def value_colors(values, vmax):
    """(n, 3) uint8 colours of ``values`` on the blue-grey-red scale from 0
    to ``vmax`` (|value|; above vmax: red)."""
    x = np.clip(np.abs(np.asarray(values, dtype=float)) / max(float(vmax), 1e-300), 0.0, 1.0) * 2.0
    k = np.minimum(x.astype(int), 1)
    f = (x - k)[:, None]
    return np.round(VALUE_COLORS[k] * (1 - f) + VALUE_COLORS[k + 1] * f).astype(np.uint8)


def shown_value(v):
    """A panel value: 4 significant digits, round-off (|v| < 1e-9) as 0."""
    return f"{v if abs(v) >= 1e-9 else 0.0:.4g}"


def grid_segments(size, cell):
    """(S, 2, 3) float32 [m]: the lines of a square grid of side ``size``
    and spacing ``cell`` in the xy plane, centred on the origin."""
    k = np.linspace(-0.5 * size, 0.5 * size, int(round(size / cell)) + 1)
    zero, end = np.zeros_like(k), np.full_like(k, 0.5 * size)
    along_y = np.stack([np.c_[k, -end, zero], np.c_[k, end, zero]], axis=1)
    return np.concatenate([along_y, along_y[:, :, [1, 0, 2]]]).astype(np.float32)


def polyline_segments(polylines):
    """(S, 2, 3) segments of polylines (N, 3) whose NaN rows separate pieces
    (a read-only polyline's, e.g. a mesh's cached outline, kept: a view
    drawing every frame cuts it once)."""
    segs = [_segments(P) for P in polylines]
    return np.concatenate(segs) if segs else np.zeros((0, 2, 3))


_SEGMENTS = {}           # id of a read-only polyline -> (the polyline, kept alive; its segments)


def _segments(P):
    kept = _SEGMENTS.get(id(P)) if isinstance(P, np.ndarray) and not P.flags.writeable else None
    if kept is not None and kept[0] is P:
        return kept[1]
    Q = np.asarray(P, dtype=float)
    ok = np.all(np.isfinite(Q), axis=1)
    both = ok[:-1] & ok[1:]
    out = np.stack([Q[:-1][both], Q[1:][both]], axis=1)
    if isinstance(P, np.ndarray) and not P.flags.writeable:
        if len(_SEGMENTS) >= 32:
            _SEGMENTS.pop(next(iter(_SEGMENTS)))
        _SEGMENTS[id(P)] = (P, out)
    return out


@dataclass(frozen=True)
class Control:
    """A slider of the page: ``kind`` "actuation" or "joint", ``name``
    (actuator or joint), its range [lo, hi] and step in ``unit``, the
    value it starts at."""
    kind: str
    name: str
    lo: float
    hi: float
    step: float
    unit: str
    value: float = 0.0

    @property
    def label(self):
        return f"{self.name} [{self.unit}]"


def tube_mesh(points, radii, sides=TUBE_SIDES):
    """(vertices (P*sides + 2, 3), faces (F, 3)) of a closed tube of
    radius ``radii`` (P,) [m] around the polyline ``points`` (P, 3) [m]; the
    rings are normal to the local tangent (parallel transport of one normal,
    so the tube does not twist), the ends capped."""
    P = np.asarray(points, dtype=float)
    r = np.broadcast_to(np.asarray(radii, dtype=float), (len(P),))
    if len(P) < 2:
        raise ValueError(f"points: a tube needs at least 2 points, got {len(P)}")
    d = np.gradient(P, axis=0)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    T = d / np.where(n > 0, n, 1.0)
    a = np.eye(3)[np.argmin(np.abs(T[0]))]
    N = np.empty_like(P)
    N[0] = np.cross(T[0], a)
    N[0] /= np.linalg.norm(N[0])
    for k in range(1, len(P)):
        v = N[k - 1] - (N[k - 1] @ T[k]) * T[k]
        nv = np.linalg.norm(v)
        N[k] = v / nv if nv > 1e-12 else N[k - 1]
    B = np.cross(T, N)
    ang = 2 * np.pi * np.arange(sides) / sides
    ring = np.cos(ang)[None, :, None] * N[:, None, :] + np.sin(ang)[None, :, None] * B[:, None, :]
    V = (P[:, None, :] + r[:, None, None] * ring).reshape(-1, 3)
    V = np.vstack([V, P[0], P[-1]])
    i = np.arange(len(P) - 1)[:, None] * sides
    j = np.arange(sides)[None, :]
    a0, a1 = i + j, i + (j + 1) % sides
    b0, b1 = a0 + sides, a1 + sides
    F = np.concatenate([np.stack([a0, b0, a1], -1).reshape(-1, 3), np.stack([a1, b0, b1], -1).reshape(-1, 3)])
    c0, c1 = len(P) * sides, len(P) * sides + 1
    last = (len(P) - 1) * sides
    caps0 = np.stack([np.full(sides, c0), (np.arange(sides) + 1) % sides, np.arange(sides)], -1)
    caps1 = np.stack([np.full(sides, c1), last + np.arange(sides), last + (np.arange(sides) + 1) % sides], -1)
    return V.astype(np.float32), np.concatenate([F, caps0, caps1]).astype(np.uint32)


def box_mesh(size, pose):
    """(vertices (8, 3), faces (12, 3)) of a box of ``size`` [m] (edge
    lengths along its local x, y, z) centred at ``pose`` (4x4, world),
    faces wound outwards."""
    h = 0.5 * np.asarray(size, dtype=float)
    c = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float) * h
    T = np.asarray(pose, dtype=float)
    V = c @ T[:3, :3].T + T[:3, 3]
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return V.astype(np.float32), F.astype(np.uint32)


def shape_mesh(visual, pose, sides=TUBE_SIDES):
    """(vertices, faces) of a rigid link's visual shape at ``pose`` (4x4
    world pose of the shape's centre): box (``size``), cylinder (``radius``,
    ``length`` along its local z axis, capped), sphere (``radius``)."""
    T = np.asarray(pose, dtype=float)
    shape = visual.get("shape", "box")
    if shape == "box":
        return box_mesh(visual["size"], T)
    if shape == "cylinder":
        h = 0.5 * float(visual["length"]) * T[:3, 2]
        return tube_mesh(np.array([T[:3, 3] - h, T[:3, 3] + h]), float(visual["radius"]), sides)
    if shape == "sphere":
        r = float(visual["radius"])
        t = np.linspace(-1.0, 1.0, sides)[1:-1]          # a UV sphere: rings along z, capped at the poles
        P = T[:3, 3] + np.outer(t * r, T[:3, 2])
        return tube_mesh(np.vstack([T[:3, 3] - r * T[:3, 2], P, T[:3, 3] + r * T[:3, 2]]),
                         np.r_[0.0, r * np.sqrt(1 - t ** 2), 0.0], sides)
    raise ValueError(f"visual.shape: expected box, cylinder or sphere, got {shape!r}")


FOV_DEG = 75.0                   # viser's camera: vertical field of view


def camera_framing(lo, hi):
    """(camera position, point looked at) [m] framing the box (lo, hi): seen
    from the front-left, a little above, +z up, its diagonal spanning 80 %
    of the view's height, and shifted left of the centre, clear of the
    panel on the right of the page."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    c, size = 0.5 * (lo + hi), max(float(np.linalg.norm(hi - lo)), 0.05)
    look = np.array([0.35, -0.85, 0.4]) / np.linalg.norm([0.35, -0.85, 0.4])      # camera from the target
    distance = size / (0.8 * 2.0 * np.tan(0.5 * np.radians(FOV_DEG)))
    right = np.cross(-look, [0.0, 0.0, 1.0])
    target = c + 0.2 * size * right / np.linalg.norm(right)
    return target + distance * look, target


def project(points, camera, target, width, height, fov_deg=FOV_DEG):
    """Page pixels (N, 2) of world points (N, 3) [m] seen by a perspective
    camera at ``camera`` looking at ``target``, +z up, vertical field of
    view ``fov_deg``, on a canvas of ``width`` x ``height`` pixels."""
    f = np.asarray(target, dtype=float) - np.asarray(camera, dtype=float)
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = np.atleast_2d(points) - np.asarray(camera, dtype=float)
    depth = d @ f
    k = 0.5 * height / np.tan(0.5 * np.radians(fov_deg))
    return np.c_[0.5 * width + k * (d @ r) / depth, 0.5 * height - k * (d @ u) / depth]


def wxyz(R):
    """Quaternion [w, x, y, z] of a rotation matrix (viser's convention)."""
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    return np.array([w, x, y, z])


class LiveView:
    """The browser view: a viser server on ``host:port`` (port 0: a free one)."""

    def __init__(self, port=8080, host="127.0.0.1", title="soft_twin", look_at=(0.2, 0.0, -0.1), distance=0.9):
        import viser
        self.server = viser.ViserServer(host=host, port=port, label=title, verbose=False)
        self.port = self.server.get_port()
        self.host = host
        self._lock = threading.Lock()
        self._text = self.server.gui.add_markdown("**soft_twin**: waiting for the twin ...")
        # the floor's grid as plain lines (viser's shaded grid costs a browser without a GPU a fifth of its
        # frame rate: benchmarks/bench_live_view.py)
        self._grid = self.server.scene.add_line_segments("/grid", grid_segments(1.0, 0.05), colors=GRID_COLOR,
                                                         thickness=1.0, thickness_units="screen",
                                                         position=(0.2, 0.0, -0.5))
        self.server.scene.set_up_direction("+z")
        # lit without shadows or an environment map (a sky-and-ground light instead): a browser without a
        # GPU (software WebGL) renders the arm at 35-40 frames a second instead of 18
        # (benchmarks/bench_live_view.py)
        self.server.scene.configure_default_lights(True, cast_shadow=False)
        self.server.scene.configure_environment_map(hdri=None)
        self.server.scene.add_light_hemisphere("/light_fill", sky_color=(255, 255, 255), ground_color=(150, 140, 130),
                                               intensity=1.5)
        # the camera of every new page: from the front-left, a little above, on the arm
        c = np.asarray(look_at, dtype=float)
        self.server.initial_camera.look_at = tuple(c)
        self.server.initial_camera.position = tuple(c + distance * np.array([0.35, -0.85, 0.4]))
        self._n_links = self._n_shapes = self._n_joints = 0
        self._sent = {}                  # scene node -> the data last sent
        self.updates = 0
        self._controls = []              # the GUI handles of set_controls
        self._trail = collections.deque()    # (t [s] or a count, tip position) of the tip path
        self._sliders = {}               # (kind, name) -> (slider handle, Control)
        self._touched = {}               # id(GUI handle) -> time.monotonic() of the page's last input to it
        self._paused_box = None
        self.control_events = 0          # values sent by the page's controls
        self._on_pick = None             # a click on the robot: on_pick(ray origin, ray direction)

    def set_controls(self, controls, on_value, on_pause=None, on_step=None, on_reset=None, on_time_scale=None,
                     time_scale=1.0):
        """The page's controls, replacing any before: a folder "drive the
        twin" with a slider per :class:`Control` (``on_value(control,
        value)`` when the page moves it), a "paused" checkbox
        (``on_pause(bool)``), "step" and "reset" buttons (``on_step()``,
        ``on_reset()``) and a time-scale slider (``on_time_scale(x)``, twin s
        per wall s). A callback left None leaves its control out."""
        gui = self.server.gui
        with self._lock:
            for h in self._controls:
                h.remove()
            self._controls, self._sliders, self._paused_box = [], {}, None
            self._touched = {}           # (keyed by id(): the removed handles' ids may be taken again)
            hook = self._page_input

            if on_pause or on_step or on_reset or on_time_scale:
                folder = gui.add_folder("run", order=1.0)
                self._controls.append(folder)
                with folder:
                    if on_pause:
                        self._paused_box = gui.add_checkbox("paused", False, hint="~/pause: stop stepping (inputs wait)")
                        hook(self._paused_box, on_pause)
                    if on_step:
                        b = gui.add_button("step", hint="~/step: one step while paused")
                        b.on_click(lambda _: (self._count(), on_step()))
                        self._controls.append(b)
                    if on_reset:
                        b = gui.add_button("reset", hint="~/reset: back to rest, no input, t = 0")
                        b.on_click(lambda _: (self._count(), on_reset()))
                        self._controls.append(b)
                    if on_time_scale:
                        hook(gui.add_slider("time scale [twin s / wall s]", 0.05, 1.0, 0.05, float(time_scale),
                                            hint="slow motion below 1 (parameter time_scale)"), on_time_scale)
            if controls:
                folder = gui.add_folder("drive the twin", order=2.0)
                self._controls.append(folder)
                with folder:
                    for c in controls:
                        h = gui.add_slider(c.label, float(c.lo), float(c.hi), float(c.step),
                                           float(min(max(c.value, c.lo), c.hi)),
                                           hint=f"{c.kind} {c.name}: {c.lo:g} to {c.hi:g} {c.unit}")
                        hook(h, lambda v, c=c: on_value(c, float(v)))
                        self._sliders[(c.kind, c.name)] = (h, c)

    def _follow(self, kind, values):
        """Move the sliders of ``kind`` to the twin's values {name: value}
        (commands from topics or plans; a value off the slider's range
        pins it at the end), under the lock. A slider the page moved in
        the last FOLLOW_HOLD_S is left to the page: its command may not
        have reached the twin yet, and writing the twin's older value back
        snapped the slider back under the user's hand (a drag ended at 0 N
        on a loaded machine); after that it shows the twin's value again."""
        now = time.monotonic()
        for name, v in values.items():
            h, c = self._sliders.get((kind, name), (None, None))
            if h is not None and now - self._touched.get(id(h), -np.inf) >= FOLLOW_HOLD_S:
                v = float(min(max(v, c.lo), c.hi))
                if abs(h.value - v) > 0.5 * c.step:
                    h.value = v

    def _count(self):
        self.control_events += 1

    def _page_input(self, handle, call):
        """``call(value)`` when the page changes GUI input ``handle`` (not
        when this view sets it, following the twin: no echo); the handle
        kept with the controls (removed with them). Returns the handle."""
        def run(event):
            if event.client is not None:
                self._touched[id(handle)] = time.monotonic()
                self.control_events += 1
                call(event.target.value)
        handle.on_update(run)
        self._controls.append(handle)
        return handle

    def set_target(self, position, on_move, on_apply, modes=None, on_mode=None, scale=0.08, on_plan=None):
        """A draggable gizmo at ``position`` [m] (moved along its axes or
        planes; ``on_move(position, phase)`` while it is dragged, phase
        "start", "update" or "end") and a "target" folder: a menu of what
        dragging does (``modes``; ``on_mode(mode)``), the answer
        (:meth:`show_ik`), an "apply" button (``on_apply()``) and, given
        ``on_plan``, a "plan a line here" button (``on_plan()``)."""
        gui, sc = self.server.gui, self.server.scene
        with self._lock:
            handle = self._target = sc.add_transform_controls(
                "/target", scale=scale, disable_rotations=True, position=tuple(np.asarray(position, dtype=float)))

            @handle.on_update
            def _(event):
                self.control_events += 1
                on_move(np.array(event.target.position, dtype=float), getattr(event, "phase", "update"))
            folder = gui.add_folder("target", order=2.5)
            self._controls += [handle, folder]
            with folder:
                if modes:
                    self._page_input(gui.add_dropdown("drag to", tuple(modes), initial_value=modes[0]), on_mode)
                self._ik_text = gui.add_markdown("drag the gizmo at the tip: inverse kinematics to its position")
                b = gui.add_button("apply", hint="send the inputs that reach the target, as the sliders do")
                b.on_click(lambda _: (self._count(), on_apply()))
                self._controls += [self._ik_text, b]
                if on_plan is not None:
                    p = gui.add_button("plan a line here", hint="plan the tip along a straight line to the "
                                                                "target (5 cm/s) and run the plan")
                    p.on_click(lambda _: (self._count(), on_plan()))
                    self._controls.append(p)

    def set_pick(self, on_pick):
        """A click in the scene calls ``on_pick(origin, direction)`` with the
        click's ray (world, [m]; the caller finds what it hits). The scene's
        click, not a mesh's: the members' meshes are sent again as they
        move, and a press on one and the release on its successor made no
        click."""
        with self._lock:
            first = self._on_pick is None
            self._on_pick = on_pick
            if first:
                @self.server.scene.on_click()
                def _(event):
                    self.control_events += 1
                    self._on_pick(np.array(event.ray_origin, dtype=float),
                                  np.array(event.ray_direction, dtype=float))

    def move_target(self, position):
        """Put the gizmo at ``position`` [m] (e.g. back on the tip)."""
        with self._lock:
            self._target.position = tuple(np.asarray(position, dtype=float))

    def say_target(self, message):
        """The "target" folder's line."""
        with self._lock:
            self._ik_text.content = message

    def show_ik(self, target, achieved, message, ghost=None):
        """The answer of the target's inverse kinematics: the tip it reaches
        (``achieved`` [m], a sphere; None: none), ``message`` and the shape
        it puts the robot in (``ghost``: polylines (N, 3) [m], drawn as
        violet lines until the next answer or "apply"; None: none)."""
        with self._lock:
            if achieved is not None:
                self.server.scene.add_icosphere("/target_reached", radius=0.006, color=TRAIL_COLOR,
                                                position=tuple(np.asarray(achieved, dtype=float)))
            t = np.asarray(target, dtype=float)
            self._ik_text.content = (f"target [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m: {message}")
        self.show_ghost(ghost)

    def show_ghost(self, polylines):
        """Draw ``polylines`` as the IK answer's ghost (None: remove it)."""
        with self._lock:
            if polylines is None:
                self._remove("/target_ghost")
                return
            seg = polyline_segments(polylines)
            if len(seg):
                self.server.scene.add_line_segments("/target_ghost", seg, colors=GHOST_COLOR, thickness=4.0,
                                                    thickness_units="screen")

    def set_view_options(self, colourings, on_colour, on_trail, trail=True, on_routes=None, routes=True,
                         on_frames=None, frames=False):
        """A "see" folder: a "colour by" menu (``colourings``: labels with
        units, "none" first; ``on_colour(label)``), a "tip path" box
        (``on_trail(bool)``) and, given their callbacks, "actuators' routes"
        and "frames" boxes."""
        gui = self.server.gui
        with self._lock:
            folder = gui.add_folder("see", order=3.0)
            self._controls.append(folder)
            with folder:
                self._page_input(gui.add_dropdown("colour by", tuple(colourings), initial_value=colourings[0]),
                                 on_colour)
                self._page_input(gui.add_checkbox("tip path", bool(trail), hint="the last 10 s"), on_trail)
                if on_routes is not None:
                    self._page_input(gui.add_checkbox("actuators' routes", bool(routes),
                                                      hint="tendons (teal) and chambers (blue) through the "
                                                           "cross-sections"), on_routes)
                if on_frames is not None:
                    self._page_input(gui.add_checkbox("frames", bool(frames),
                                                      hint="every named frame's axes (x red, y green, z blue)"),
                                     on_frames)

    def set_playback(self, t0, t1, step, signals, on_play, on_seek, on_speed, on_signal):
        """The controls of a run played back (:mod:`soft_twin_core.viz.playback`):
        a "playing" box (``on_play(bool)``), a "time [s]" slider from t0 to t1
        to scrub (``on_seek(t)``), a "speed [x]" slider (``on_speed(x)``, run s
        per wall s) and a "signal" menu of ``signals`` (labels with units;
        ``on_signal(label)``) plotted below, up to the time shown
        (:meth:`show_playback`)."""
        from viser import uplot
        gui = self.server.gui
        with self._lock:
            folder = gui.add_folder("playback", order=1.0)
            self._controls.append(folder)
            hook = self._page_input
            with folder:
                hook(gui.add_checkbox("playing", True), on_play)
                self._time_slider = hook(gui.add_slider("time [s]", float(t0), float(max(t1, t0 + step)), float(step),
                                                        float(t0)), on_seek)
                hook(gui.add_slider("speed [x]", 0.05, 2.0, 0.05, 1.0, hint="run seconds per wall second"),
                     on_speed)
                labels = tuple(signals)
                hook(gui.add_dropdown("signal", labels, initial_value=labels[0]), on_signal)
                self._plot = gui.add_uplot(
                    data=(np.zeros(1), np.zeros(1)),
                    series=(uplot.Series(label="t [s]"), uplot.Series(label=labels[0], stroke="#d97333", width=2)),
                    scales={"x": uplot.Scale(time=False, auto=False, range=(float(t0), float(max(t1, t0 + step))))},
                    axes=(uplot.Axis(label="t [s]"), uplot.Axis(label=labels[0])), aspect=1.6)
                self._controls.append(self._plot)
            self._plot_label = labels[0]

    def show_playback(self, t, times, label, values):
        """The playback's state at run time ``t`` [s]: the time slider there,
        the plot of signal ``label`` over ``times`` up to it (``values``: the
        signal at ``times``)."""
        from viser import uplot
        with self._lock:
            if abs(self._time_slider.value - t) >= 0.5 * self._time_slider.step:
                self._time_slider.value = float(min(max(t, self._time_slider.min), self._time_slider.max))
            k = int(np.searchsorted(times, t, side="right"))
            x, y = np.asarray(times[:max(k, 1)], dtype=float), np.asarray(values[:max(k, 1)], dtype=float)
            if label != self._plot_label:
                self._plot.series = (uplot.Series(label="t [s]"), uplot.Series(label=label, stroke="#d97333", width=2))
                self._plot.axes = (uplot.Axis(label="t [s]"), uplot.Axis(label=label))
                self._plot_label = label
            if self._changed("/gui/plot", x, y, np.frombuffer(label.encode(), np.uint8)):
                self._plot.data = (x, y)

    def frame(self, lo, hi):
        """Aim the camera of every new page at the box (lo, hi) [m] (a robot's
        extent, e.g. :func:`scene.bounds`) from the front-left, a little
        above, and put the grid just under it."""
        position, target = camera_framing(lo, hi)
        self.server.initial_camera.look_at = tuple(target)
        self.server.initial_camera.position = tuple(position)
        c = 0.5 * (np.asarray(lo, dtype=float) + np.asarray(hi, dtype=float))
        self._grid.position = (float(c[0]), float(c[1]), float(lo[2]) - 0.02)

    @property
    def url(self):
        return f"http://{self.host}:{self.port}"

    def show(self, snap, radii=0.01, base_pose=None, tip_pose=None, tip_force=None, actuation=None,
             force_scale=0.5, text="", joints=None, units=None, paused=None, values=None, trail=False,
             contacts=None, point_forces=None, routes=None, frames=None):
        """Draw one :class:`scene.Snapshot`: a tube per member (radii [m]: one
        value or one per point of each member, a list per member), links as
        bars, the base and tip frames (4x4 poses, world), the tip force [N]
        as an arrow of ``force_scale`` m per N, the actuation values and the
        joint positions (``joints``: {name: value}); ``units``: {actuator or
        joint name: unit} for the panel (default N for actuators, rad for
        joints); ``paused``: tick the page's "paused" box so. The sliders
        follow the actuation and joint positions. ``values``: (label with
        unit, [per member, a value per backbone point]): the members
        coloured by them (:func:`value_colors`, from 0 to the largest |value|
        shown, given in the panel); ``trail``: draw the tip's path over the
        last TRAIL_SECONDS; ``contacts``: (positions (K, 3) [m], forces (K, 3)
        [N]) drawn as arrows of ``force_scale`` m per N; the snapshot's
        obstacles are outlined; ``point_forces``: [(point name, position,
        force)] the loads on other points than the tip, drawn and listed;
        ``routes``: [(actuator kind, polyline (K, 3))] drawn as lines
        (tendons green, chambers blue); ``frames``: {name: 4x4} drawn as
        small axes (None: none)."""
        sc = self.server.scene
        with self._lock:
            vmax = None
            if values is not None:
                vmax = max([float(np.max(np.abs(v), initial=0.0)) for v in values[1]] + [1e-300])
            for k, P in enumerate(snap.members):
                r = radii[k] if isinstance(radii, (list, tuple)) else radii
                if len(P) >= 2:
                    V, F = tube_mesh(P, r)
                    vk = None if values is None or k >= len(values[1]) else np.asarray(values[1][k], dtype=float)
                    if vk is not None and len(vk) == len(P):
                        C = value_colors(np.r_[np.repeat(vk, TUBE_SIDES), vk[0], vk[-1]], vmax)
                        if self._changed(f"/twin/member_{k}", V, F, C):
                            self._add_coloured_mesh(f"/twin/member_{k}", V, F, C)
                    elif self._changed(f"/twin/member_{k}", V, F):
                        sc.add_mesh_simple(f"/twin/member_{k}", V, F, color=TUBE_COLOR, flat_shading=False)
            for k, seg in enumerate(snap.links):
                if self._changed(f"/twin/link_{k}", seg):
                    sc.add_line_segments(f"/twin/link_{k}", np.asarray(seg, np.float32)[None], colors=LINK_COLOR,
                                         thickness=6.0, thickness_units="screen")
            for k in range(len(snap.links), self._n_links):
                self._remove(f"/twin/link_{k}")
            self._n_links = len(snap.links)
            # articulated robots: the links' visual shapes, the rigid joints and their axes
            for k, (vis, T) in enumerate(snap.shapes):
                V, F = shape_mesh(vis, T)
                if self._changed(f"/twin/shape_{k}", V, F):
                    sc.add_mesh_simple(f"/twin/shape_{k}", V, F, color=SHAPE_COLOR, flat_shading=True)
            for k in range(len(snap.shapes), self._n_shapes):
                self._remove(f"/twin/shape_{k}")
            self._n_shapes = len(snap.shapes)
            for k, p in enumerate(snap.joints):
                if self._changed(f"/twin/joint_{k}", p):
                    sc.add_icosphere(f"/twin/joint_{k}", radius=0.006, color=JOINT_COLOR, position=tuple(p))
            for k in range(len(snap.joints), self._n_joints):
                self._remove(f"/twin/joint_{k}")
            self._n_joints = len(snap.joints)
            if snap.joint_axes and self._changed("/twin/joint_axes", *snap.joint_axes):
                sc.add_line_segments("/twin/joint_axes", np.asarray(snap.joint_axes, np.float32),
                                     colors=JOINT_COLOR, thickness=3.0, thickness_units="screen")
            for name, T in (("base", base_pose), ("tip", tip_pose)):
                if T is not None and self._changed(f"/twin/{name}_frame", T):
                    T = np.asarray(T, dtype=float)
                    sc.add_frame(f"/twin/{name}_frame", wxyz=wxyz(T[:3, :3]), position=T[:3, 3],
                                 axes_length=0.05, axes_radius=0.002)
            self._draw_trail(tip_pose, snap.time, trail)
            self._draw_world(snap, contacts, force_scale)
            if tip_force is not None and tip_pose is not None:
                p0 = np.asarray(tip_pose, dtype=float)[:3, 3]
                seg = np.array([[p0, p0 + force_scale * np.asarray(tip_force, dtype=float)]], np.float32)
                if self._changed("/twin/tip_force", seg):
                    sc.add_line_segments("/twin/tip_force", seg, colors=FORCE_COLOR, thickness=5.0,
                                         thickness_units="screen")
            lines = [f"**soft_twin** {snap.caption}  {text}".rstrip()]
            if vmax is not None:
                lines.append(f"- colour: {values[0]}, blue 0 to red {vmax:.4g}")
            units = units or {}
            if actuation:
                lines += [f"- `{k}`: {shown_value(v)} {units.get(k, 'N')}" for k, v in actuation.items()]
            if joints:
                lines += [f"- joint `{k}`: {shown_value(v)} {units.get(k, 'rad')}" for k, v in joints.items()]
            if tip_force is not None:
                f = np.asarray(tip_force, dtype=float)
                lines.append(f"- tip force: [{f[0]:.3g}, {f[1]:.3g}, {f[2]:.3g}] N")
            self._draw_point_forces(point_forces or (), force_scale, lines)
            self._draw_routes(routes or ())
            self._draw_frames(frames or {})
            self._follow("actuation", actuation or {})
            self._follow("joint position", joints or {})
            if paused is not None and self._paused_box is not None and self._paused_box.value != bool(paused):
                self._paused_box.value = bool(paused)
            content = "\n".join(lines)
            if content != self._text.content:
                self._text.content = content
            self.updates += 1

    def _add_coloured_mesh(self, name, V, F, C):
        import trimesh
        mesh = trimesh.Trimesh(vertices=V, faces=F, vertex_colors=np.c_[C, np.full(len(C), 255, np.uint8)],
                               process=False)
        self.server.scene.add_mesh_trimesh(name, mesh)

    def _draw_trail(self, tip_pose, t, on):
        """The tip's path over the last TRAIL_SECONDS (a point per TRAIL_STEP_M
        moved), or none (``on`` false: the path forgotten)."""
        sc, trail = self.server.scene, self._trail
        if not on or tip_pose is None:
            trail.clear()
            if "/twin/tip_path" in self._sent:
                self._remove("/twin/tip_path")
            return
        p = np.asarray(tip_pose, dtype=float)[:3, 3]
        t = float(t) if t is not None else float(self.updates)
        if trail and t < trail[-1][0]:                 # time went back (a reset, a loop): start again
            trail.clear()
        if not trail or np.linalg.norm(p - trail[-1][1]) >= TRAIL_STEP_M:
            trail.append((t, p.copy()))
        while trail and trail[0][0] < t - TRAIL_SECONDS:
            trail.popleft()
        if len(trail) >= 2:
            P = np.array([q for _, q in trail], np.float32)
            seg = np.stack([P[:-1], P[1:]], axis=1)
            if self._changed("/twin/tip_path", seg):
                sc.add_line_segments("/twin/tip_path", seg, colors=TRAIL_COLOR, thickness=3.0,
                                     thickness_units="screen")
        elif "/twin/tip_path" in self._sent:
            self._remove("/twin/tip_path")

    def _draw_point_forces(self, point_forces, force_scale, lines):
        """The loads on other points than the tip: arrows, and a panel line each."""
        if point_forces:
            seg = np.array([[p, np.asarray(p) + force_scale * np.asarray(f)] for _, p, f in point_forces],
                           np.float32)
            if self._changed("/twin/point_forces", seg):
                self.server.scene.add_line_segments("/twin/point_forces", seg, colors=FORCE_COLOR, thickness=5.0,
                                                    thickness_units="screen")
            lines += [f"- force on `{n}`: [{f[0]:.3g}, {f[1]:.3g}, {f[2]:.3g}] N" for n, _, f in point_forces]
        elif "/twin/point_forces" in self._sent:
            self._remove("/twin/point_forces")

    def _draw_routes(self, routes):
        """The actuators' routes: one node of segments per kind."""
        for kind, node, color in (("tendon", "/twin/tendons", TENDON_COLOR), ("chamber", "/twin/chambers",
                                                                            CHAMBER_COLOR)):
            lines = [P for k, P in routes if k == kind]
            if lines:
                seg = np.concatenate([np.stack([P[:-1], P[1:]], axis=1) for P in lines]).astype(np.float32)
                if self._changed(node, seg):
                    self.server.scene.add_line_segments(node, seg, colors=color, thickness=2.0,
                                                        thickness_units="screen")
            elif node in self._sent:
                self._remove(node)

    def _draw_frames(self, frames):
        """Every named frame's axes (those no longer asked for removed)."""
        for name, T in frames.items():
            T = np.asarray(T, dtype=float)
            if self._changed(f"/twin/frames/{name}", T):
                self.server.scene.add_frame(f"/twin/frames/{name}", wxyz=wxyz(T[:3, :3]), position=T[:3, 3],
                                            axes_length=0.03, axes_radius=0.0012)
        for node in [n for n in self._sent if n.startswith("/twin/frames/") and n[13:] not in frames]:
            self._remove(node)

    def _draw_world(self, snap, contacts, force_scale):
        """The obstacles' outlines and the contact forces as arrows."""
        sc = self.server.scene
        segs = polyline_segments(getattr(snap, "obstacles", ()) or ()).astype(np.float32)
        if len(segs) and self._changed("/world/obstacles", segs):
            sc.add_line_segments("/world/obstacles", segs, colors=OBSTACLE_COLOR, thickness=2.0,
                                 thickness_units="screen")
        p, f = (np.zeros((0, 3)), np.zeros((0, 3))) if contacts is None else map(np.asarray, contacts)
        if len(p):
            seg = np.stack([p, p + force_scale * f], axis=1).astype(np.float32)
            if self._changed("/world/contact_forces", seg):
                sc.add_line_segments("/world/contact_forces", seg, colors=CONTACT_COLOR, thickness=4.0,
                                     thickness_units="screen")
        elif "/world/contact_forces" in self._sent:
            self._remove("/world/contact_forces")

    def _changed(self, name, *arrays):
        """True (and remembered) when the data of scene node ``name`` differ
        from what was last sent: an unchanged state (a quasi-static twin
        republishing) sends nothing, so a slow browser never falls behind."""
        key = b"".join(np.ascontiguousarray(a, dtype=np.float64).tobytes() for a in arrays)
        if self._sent.get(name) == key:
            return False
        self._sent[name] = key
        return True

    def _remove(self, name):
        self.server.scene.remove_by_name(name)
        self._sent.pop(name, None)

    def close(self):
        self.server.stop()
