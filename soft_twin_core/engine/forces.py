"""Applied forces on the multibody engine: point and distributed loads on a
path, gravity, tendons and chambers.

* Loads (:class:`soft_twin_core.engine.loads.Loads`: point and distributed wrenches
  at arc lengths s of a path, dead or follower; a gravity switch or scale)
  become :class:`kernels.data.LoadArrays`: one point wrench per load point
  on (soft joint, abscissa), distributed loads by Gauss quadrature over each
  section's overlap with their span (weights folded in).
* Actuators (tendons with straight, converging or helical routing;
  chambers) act on the strains of the sections they cross. The exact
  frictionless tendon gives the joint-space force density
  ``-c u [t; d x t]`` with t the unit tangent of the tendon path at offset
  d(s), ``t ~ f_u + f_w x d + d'`` (c = 1 for a tendon of tension u, -A for a
  chamber of area A at pressure u), integrated over the routed span by Gauss
  quadrature: :class:`ActuatorArrays` holds the geometry,
  :func:`actuation_pass` the compiled sum. A quadrature point reads its
  section's strain, or on field pairs (a fourth-order segment's intervals,
  :class:`multibody.FieldPair`) the field's, a combination of up to
  :data:`MIXED` sections' strains on which its force then acts
  (:class:`_Field`). Tendons of the point-moment model
  (slides part C, model (b)) are follower point moments at their
  termination instead.
* Tendon-sheath friction (a tendon's ``friction`` mu > 0): a tendon pulled
  in slides along its sheath and the capstan law lowers its tension along
  the routing, ``T(s) = u exp(-mu theta(s))``, with ``theta(s) = int_start^s
  |dt_w/ds| ds`` the angle its world tangent t_w has turned (the wrap angle;
  :func:`wrap_rate` is the integrand). The tendon's force on the body,
  ``(T t_w)'`` per unit length (normal pressure ``T t_w'`` and sheath friction
  ``T' t_w``, with |T'| = mu |T t_w'|, Coulomb at slip) plus the pull at the
  termination, has the generalised force ``-int T(s) (dp'/dq)^T t_w ds``:
  the frictionless density with u replaced by T(s). theta is integrated
  between the quadrature points on extra nodes (:class:`ActuatorArrays`
  ``node_*``); it depends on the strains of every section before s, so the
  tangent gains a lower-triangular coupling along the tendon
  (:func:`sheath_tangent_pass`).
"""

from dataclasses import replace

import numba as nb
import numpy as np
from numba.experimental import structref

from soft_twin_core.engine.algorithms import point_jacobian
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import ArraysRef, ArraysType, LoadArrays, declare
from soft_twin_core.engine.kernels.spatial import _jit, _jit_inline, _jit_inner
from soft_twin_core.engine.loads import Loads, actuator_point_loads

ACTUATOR_FIELDS = (
    "joint",      # (P,) soft joint of each tendon quadrature point
    "mixed",      # (P, MIXED) on field pairs (multibody.FieldPair): the joints whose strains the point reads, -1 after
    "mix",        # (P, MIXED): the point's strain sum_h mix[h] strain[mixed[h]] (off pairs: [joint], (1, 0, ..))
    "d", "dd",    # (P, 3) offset d(s) and d'(s) in the cross-section frame [m, -]
    "unit",       # (P, n_actuators): coefficient per unit input (-c w: m per N or m^3 per Pa... see module)
    "mu",         # (P,) sheath friction coefficient of the point's tendon (0: frictionless)
    "first",      # (P,) 1 at the first point of each actuator (its wrap angle starts at 0), else 0
    "node_ptr",   # (P + 1,) the wrap-angle nodes between point p - 1 (or start) and p: node_ptr[p]:node_ptr[p+1]
    "node_mixed", "node_mix",  # (N, MIXED) each wrap-angle node's strain, as "mixed" and "mix" a point's
    "node_d", "node_dd", "node_ddd",  # (N, 3) d, d', d'' at the node [m, -, 1/m]
    "node_w",     # (N,) quadrature weight of the node [m]
)


@structref.register
class ActuatorArraysType(ArraysType):
    pass


class ActuatorArrays(ArraysRef):
    """The actuators' quadrature geometry (:data:`ACTUATOR_FIELDS`) as the kernels take it."""
    FIELDS = ACTUATOR_FIELDS


declare(ActuatorArrays, ActuatorArraysType, ACTUATOR_FIELDS)


@nb.njit(cache=True)
def _make_actuator_ref(joint, mixed, mix, d, dd, unit, mu, first, node_ptr, node_mixed, node_mix, node_d, node_dd,
                       node_ddd, node_w):
    return ActuatorArrays(joint, mixed, mix, d, dd, unit, mu, first, node_ptr, node_mixed, node_mix, node_d, node_dd,
                          node_ddd, node_w)


ActuatorArrays.make = _make_actuator_ref

WRAP_NODES = 3     # Gauss points per piece of the wrap-angle integral (exact for straight routings)
MIXED = 4          # the sections a quadrature point's strain may combine (two field pairs: a cubic through 4 points)


def _gauss_on_path(model, path, start, end):
    """(joint, x, s, w) Gauss points of each section of ``path`` over its
    overlap with [start, end] (the section's own point count)."""
    js, xs, ss, ws = [], [], [], []
    for k, j in enumerate(path.joints):
        s, w = _section_gauss(model, j, path.s_starts[k], path.lengths[k], start, end)
        js += [j] * len(s)
        xs.append(s - path.s_starts[k])
        ss.append(s)
        ws.append(w)
    if not js:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0)
    return np.array(js, np.int64), np.concatenate(xs), np.concatenate(ss), np.concatenate(ws)


def _section_gauss(model, j, s0, length, start, end):
    """(s, w): the Gauss points (the section's own count) and weights of
    soft joint j, from s0 over ``length`` on its path, on its overlap with
    [start, end] (none without one)."""
    a, b = max(s0, start), min(s0 + length, end)
    if b <= a:
        return np.zeros(0), np.zeros(0)
    xg, wg = np.polynomial.legendre.leggauss(model.joints[j].section.quadrature_points)
    return 0.5 * (a + b) + 0.5 * (b - a) * xg, 0.5 * (b - a) * wg


class _Field:
    """The field pairs (:class:`multibody.FieldPair`) along ``path``: where
    their spans lie, and the field's strain at an arc length inside one as
    a combination of sections' strains (:meth:`mix`)."""

    def __init__(self, model, path):
        self.path = path
        self.pairs = {fp.joints[0]: fp for fp in model.field_pairs}
        self.second = {fp.joints[1] for fp in model.field_pairs}
        self.field_of = {j: f for f, ef in enumerate(model.elastic_fields) for j in ef.joints}

    def span(self, k):
        """(a, b, (Y_1, Y_2)): the span on the path of the pair starting at
        the path's joint k, and its 2-point Gauss points [m]."""
        a = self.path.s_starts[k]
        b = a + self.path.lengths[k] + self.path.lengths[k + 1]
        return a, b, 0.5 * (a + b) + 0.5 * (b - a) * np.array([-1.0, 1.0]) / np.sqrt(3.0)

    def mix(self, k, s):
        """(mixed (MIXED,), mix (len(s), MIXED)): the field at arc lengths s
        inside the span of the pair at the path's joint k, ``sum_h mix[h]
        strain[mixed[h]]``: the cubic through the Gauss points of the pair
        and a neighbouring pair of the same elastic field (exact at Y_1,
        Y_2; a line through two would leave a partial span third order),
        or the line through the pair's own when it has no neighbour."""
        joints = self.path.joints
        j = joints[k]
        mixed = np.full(MIXED, -1)
        mixed[:2] = self.pairs[j].joints
        ys, rows = self.span(k)[2], self.pairs[j].field
        near = [o for o in (2, -2) if 0 <= k + o < len(joints) - 1 and joints[k + o] in self.pairs
                and self.field_of.get(joints[k + o]) == self.field_of.get(j)]
        if near:
            other = self.pairs[joints[k + near[0]]]
            mixed[2:] = other.joints
            ys = np.concatenate([ys, self.span(k + near[0])[2]])
            rows = np.block([[rows, np.zeros((2, 2))], [np.zeros((2, 2)), other.field]])
        lagrange = np.array([[np.prod([(x - ys[m]) / (ys[i] - ys[m]) for m in range(len(ys)) if m != i])
                              for i in range(len(ys))] for x in np.atleast_1d(s)])
        mix = np.zeros((lagrange.shape[0], MIXED))
        mix[:, :rows.shape[1]] = lagrange @ rows
        return mixed, mix


def _own_strain(js):
    """(mixed, mix) of points that read their own sections' strains ``js``."""
    mixed = np.full((len(js), MIXED), -1)
    mixed[:, 0] = js
    mix = np.zeros((len(js), MIXED))
    mix[:, 0] = 1.0
    return mixed, mix


def _field_points(model, path, start, end):
    """(joint, mixed (n, MIXED), mix (n, MIXED), s, w): the quadrature
    points of an actuator over [start, end] on ``path``: each section's
    Gauss points (:func:`_gauss_on_path`; the strain its own), but on a
    field pair (:class:`multibody.FieldPair`) the field's (:class:`_Field`):
    over the pair's whole span its 2-point Gauss points Y_1, Y_2, over part
    of it (an actuator's end) Gauss points on the overlap."""
    field = _Field(model, path)
    out = [[], [], [], [], []]
    for k, j in enumerate(path.joints):
        if j in field.second:
            continue
        if j not in field.pairs:
            s, w = _section_gauss(model, j, path.s_starts[k], path.lengths[k], start, end)
            for lst, val in zip(out, (np.full(len(s), j), *_own_strain(np.full(len(s), j)), s, w)):
                lst.append(val)
            continue
        a, b, y = field.span(k)
        lo, hi = max(a, start), min(b, end)
        if hi <= lo:
            continue
        if lo == a and hi == b:
            s, w = y, np.full(2, 0.5 * (b - a))
        else:
            xg, wg = np.polynomial.legendre.leggauss(2)
            s, w = 0.5 * (lo + hi) + 0.5 * (hi - lo) * xg, 0.5 * (hi - lo) * wg
        mixed, mix = field.mix(k, s)
        if lo == a and hi == b:              # at Y_1, Y_2 the pair alone (the cubic's other weights are 0)
            mixed[2:], mix[:, 2:] = -1, 0.0
        for lst, val in zip(out, (np.full(len(s), j), np.tile(mixed, (len(s), 1)), mix, s, w)):
            lst.append(val)
    if not out[0]:
        return np.zeros(0, np.int64), np.zeros((0, MIXED), np.int64), np.zeros((0, MIXED)), np.zeros(0), np.zeros(0)
    return (np.concatenate(out[0]).astype(np.int64), np.concatenate(out[1]).astype(np.int64),
            np.concatenate(out[2]), np.concatenate(out[3]), np.concatenate(out[4]))


def _wrap_nodes(model, act, path, a, b):
    """(mixed (N, MIXED), mix (N, MIXED), d, d', d'', w) Gauss nodes of the
    wrap-angle integral over [a, b] on ``path``, split at section ends
    (the strain is constant on each piece) or, on field pairs, at their
    spans' ends (the field smooth on each; :class:`_Field`)."""
    field = _Field(model, path)
    out = [[], [], [], [], [], []]
    for k, j in enumerate(path.joints):
        if j in field.second:
            continue
        lo0, hi0 = (field.span(k)[:2] if j in field.pairs else
                    (path.s_starts[k], path.s_starts[k] + path.lengths[k]))
        lo, hi = max(lo0, a), min(hi0, b)
        if hi <= lo:
            continue
        xg, wg = np.polynomial.legendre.leggauss(WRAP_NODES)
        s = 0.5 * (lo + hi) + 0.5 * (hi - lo) * xg
        if j in field.pairs:
            mixed, mix = field.mix(k, s)
            mixed = np.tile(mixed, (len(s), 1))
        else:
            mixed, mix = _own_strain(np.full(len(s), j))
        d, dd = act.offset_at(s)
        for lst, val in zip(out, (mixed, mix, d, dd, act.offset_second_derivative(s), 0.5 * (hi - lo) * wg)):
            lst.append(val)
    if not out[0]:
        return (np.zeros((0, MIXED), np.int64), np.zeros((0, MIXED)), *(np.zeros((0, 3)),) * 3, np.zeros(0))
    return (np.concatenate(out[0]).astype(np.int64), *(np.concatenate(x) for x in out[1:]))


def actuator_arrays(model):
    """Quadrature geometry of the model's distributed actuators (tendon model
    "distributed") on their path, with the wrap-angle nodes of the tendons
    with sheath friction."""
    J, J2, MIX, D, DD, U, MU, FIRST, COUNT = [], [], [], [], [], [], [], [], []
    nodes = [[], [], [], [], [], []]
    na = len(model.actuators)
    for k, a in enumerate(model.actuators):
        if a.tendon_model == "point_moment":
            continue
        path = model.path_of_actuator(k)
        if not model.field_pairs:
            j, _, s, w = _gauss_on_path(model, path, a.start, a.end)
            j2, mix = _own_strain(j)
        else:
            j, j2, mix, s, w = _field_points(model, path, a.start, a.end)
        d, dd = a.offset_at(s)
        unit = np.zeros((len(s), na))
        unit[:, k] = -a.force_per_unit_input * w
        J.append(j)
        J2.append(j2)
        MIX.append(mix)
        D.append(d)
        DD.append(dd)
        U.append(unit)
        MU.append(np.full(len(s), float(a.friction)))
        FIRST.append((np.arange(len(s)) == 0).astype(np.int64))
        for p in range(len(s)):
            if a.friction > 0:
                piece = _wrap_nodes(model, a, path, a.start if p == 0 else s[p - 1], s[p])
                for lst, val in zip(nodes, piece):
                    lst.append(val)
                COUNT.append(len(piece[0]))
            else:
                COUNT.append(0)
    if not J:
        z3 = np.zeros((0, 3))
        return ActuatorArrays.of(np.zeros(0, np.int64), np.zeros((0, MIXED), np.int64), np.zeros((0, MIXED)), z3, z3,
                                 np.zeros((0, na)), np.zeros(0), np.zeros(0, np.int64), np.zeros(1, np.int64),
                                 np.zeros((0, MIXED), np.int64), np.zeros((0, MIXED)), z3, z3, z3, np.zeros(0))
    cat3 = (lambda x: np.ascontiguousarray(np.concatenate(x)) if x else np.zeros((0, 3)))
    catm = (lambda x, t: np.ascontiguousarray(np.concatenate(x), dtype=t) if x else np.zeros((0, MIXED), t))
    return ActuatorArrays.of(np.concatenate(J), np.ascontiguousarray(np.concatenate(J2), dtype=np.int64),
                          np.ascontiguousarray(np.concatenate(MIX)), np.ascontiguousarray(np.concatenate(D)),
                          np.ascontiguousarray(np.concatenate(DD)), np.ascontiguousarray(np.concatenate(U)),
                          np.concatenate(MU), np.concatenate(FIRST),
                          np.concatenate([[0], np.cumsum(COUNT)]).astype(np.int64),
                          catm(nodes[0], np.int64), catm(nodes[1], float),
                          cat3(nodes[2]), cat3(nodes[3]), cat3(nodes[4]),
                          np.concatenate(nodes[5]) if nodes[5] else np.zeros(0))


def check_member_loads(model, loads, where="loads"):
    """ValueError naming the bad field of member loads (:class:`loads.Loads`
    point and distributed loads on the soft members, i.e. the paths, of
    ``model``): an unknown member, an arc length outside it, a wrench that
    is not 6 finite numbers, axes other than world/body, an empty span."""
    names = [p.name for p in model.paths]
    for kind, items in (("point", loads.point), ("distributed", loads.distributed)):
        for i, ld in enumerate(items):
            at = f"{where}.{kind}[{i}]"
            if ld.member is not None and ld.member not in names:
                raise ValueError(f"{at}.member: {ld.member!r} is not a soft member of the robot; members: {names}")
            if not names:
                raise ValueError(f"{at}: the robot has no soft member to load (use a load on a frame)")
            path = model.path(ld.member) if ld.member is not None else model.paths[0]
            w = np.asarray(ld.wrench, dtype=float)
            if w.shape != (6,) or not np.all(np.isfinite(w)):
                raise ValueError(f"{at}.wrench: expected 6 finite numbers [f; m], got {ld.wrench!r}")
            if ld.frame not in ("world", "body"):
                raise ValueError(f"{at}.frame: expected 'world' or 'body', got {ld.frame!r}")
            if kind == "point" and not -1e-12 <= ld.s <= path.length + 1e-12:
                raise ValueError(f"{at}.s: must lie in [0, {path.length:g}] m (member {path.name!r}), got {ld.s}")
            if kind == "distributed":
                end = path.length if ld.end is None else ld.end
                if not 0.0 <= ld.start < end <= path.length + 1e-12:
                    raise ValueError(f"{at}: need 0 <= start < end <= {path.length:g} m (member {path.name!r}), "
                                     f"got {ld.start}, {end}")


def load_arrays(model, loads=None, u=None, path_name=None):
    """LoadArrays of ``loads`` (each on its ``member``; a load without one
    on the path ``path_name``, default the first) plus the follower moments
    of point-moment tendons (on their own paths) at inputs u."""
    loads = Loads() if loads is None else loads
    default = model.path(path_name) if path_name else (model.paths[0] if model.paths else None)

    def path_of(ld):
        return model.path(ld.member) if ld.member is not None else default

    J, X, W, F = [], [], [], []
    for d in loads.distributed:
        path = path_of(d)
        j, x, _, w = _gauss_on_path(model, path, d.start, path.length if d.end is None else d.end)
        J.append(j)
        X.append(x)
        W.append(w[:, None] * np.asarray(d.wrench, float)[None, :])
        F.append(np.full(len(j), d.frame == "world"))
    points = tuple(loads.point) + (_point_moment_loads(model, u) if u is not None and model.actuators else ())
    for p in points:
        path = path_of(p)
        j, x = path.locate(np.array([min(max(float(p.s), 0.0), path.length)]))
        J.append(j)
        X.append(x)
        W.append(np.asarray(p.wrench, float).reshape(1, 6))
        F.append(np.array([p.frame == "world"]))
    if not J:
        return LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))
    return LoadArrays(np.concatenate(J).astype(np.int64), np.ascontiguousarray(np.concatenate(X)),
                      np.ascontiguousarray(np.concatenate(W)), np.concatenate(F).astype(np.bool_))


def point_moment_arrays(model, u):
    """LoadArrays of the follower moments of the point-moment tendons at
    inputs u (empty when the robot has none), each on its actuator's path."""
    has = model.__dict__.get("_has_point_moments")
    if has is None:
        has = any(a.tendon_model == "point_moment" for a in model.actuators)
        object.__setattr__(model, "_has_point_moments", has)
    if not has:
        return _NO_LOAD_ARRAYS
    return load_arrays(model, None, np.asarray(u, dtype=float))


_NO_LOAD_ARRAYS = LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))


def _point_moment_loads(model, u):
    """The follower moments of point-moment tendons (:func:`loads.actuator_point_loads`),
    each on its actuator's own path."""
    out = []
    for k, a in enumerate(model.actuators):
        if a.tendon_model != "point_moment" or u[k] == 0.0:
            continue
        one = np.zeros(len(u))
        one[k] = u[k]
        (p,) = actuator_point_loads(model, one)
        out.append(replace(p, member=model.path_of_actuator(k).name))
    return tuple(out)


def concat_loads(*lds):
    """One LoadArrays of several (empty ones left out)."""
    lds = [ld for ld in lds if ld.joint.shape[0]]
    if not lds:
        return _NO_LOAD_ARRAYS          # (empty: nothing to write into)
    if len(lds) == 1:
        return lds[0]
    return LoadArrays(np.concatenate([ld.joint for ld in lds]), np.ascontiguousarray(np.concatenate([ld.x for ld in lds])),
                      np.ascontiguousarray(np.concatenate([ld.wrench for ld in lds])),
                      np.concatenate([ld.world for ld in lds]))


def tendon_coefficients(act, u):
    """The tendon joints' coefficients ``act.unit @ u`` of the actuators'
    inputs u (:class:`ActuatorArrays` ``act``), contiguous; zeros without
    inputs."""
    unit = act.unit
    return np.ascontiguousarray(unit @ u) if u.size else np.zeros(unit.shape[0])


def gravity_of(model, loads=None):
    """Gravity vector [m/s^2] (world) the loads switch on or scale."""
    grav = True if loads is None else loads.gravity
    scale = (1.0 if grav else 0.0) if isinstance(grav, bool) else float(grav)
    return scale * np.asarray(model.gravity, dtype=float)


@_jit_inline
def _cross3(a, b):
    """a x b of two 3-tuples (or 3-arrays), a tuple."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@_jit_inline
def _dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@_jit_inline
def _wrap_parts(xi, d, dd, ddd):
    """The pieces of ``dt_w/ds = R a`` for a tendon on a section of constant
    strain xi = (nu, kappa): n = nu + kappa x d + d' (so that p' = R n),
    n' = kappa x d' + d'', t = n/|n|, b = n' - t (t . n') and
    a = kappa x t + b/|n|. Returns (a, t, |n|, b, t . n', n', kappa),
    3-tuples (scalars: no array temporaries in the passes that inline it)."""
    k = (xi[3], xi[4], xi[5])
    kd = _cross3(k, d)
    kdd = _cross3(k, dd)
    n = (xi[0] + kd[0] + dd[0], xi[1] + kd[1] + dd[1], xi[2] + kd[2] + dd[2])
    npr = (kdd[0] + ddd[0], kdd[1] + ddd[1], kdd[2] + ddd[2])
    nn = np.sqrt(_dot3(n, n))
    t = (n[0] / nn, n[1] / nn, n[2] / nn)
    tn = _dot3(t, npr)
    b = (npr[0] - t[0] * tn, npr[1] - t[1] * tn, npr[2] - t[2] * tn)
    kt = _cross3(k, t)
    a = (kt[0] + b[0] / nn, kt[1] + b[1] / nn, kt[2] + b[2] / nn)
    return a, t, nn, b, tn, npr, k


@_jit_inline
def wrap_rate(xi, d, dd, ddd):
    """|dt_w/ds| [rad/m]: how fast the tendon path's world tangent turns per
    unit arc length of the backbone, at offset d (d', d'') on a section of
    strain xi (the tendon point p = r + R d, p' = R n, t_w = R n/|n|)."""
    a = _wrap_parts(xi, d, dd, ddd)[0]
    return np.sqrt(_dot3(a, a))


@_jit_inline
def wrap_rate_gradient(xi, d, dd, ddd, out):
    """out (6,) = d wrap_rate / d xi (0 where the tendon runs straight, the
    rate's kink): along each strain component c, dn (e_c for nu; e x d for
    kappa), dn' (0; e x d'), dt = (dn - t (t . dn))/|n|,
    db = dn' - dt (t . n') - t (dt . n' + t . dn'),
    da = dk x t + kappa x dt + db/|n| - b (t . dn)/|n|^2, and
    d|a| = a . da / |a|."""
    a, t, nn, b, tn, npr, k = _wrap_parts(xi, d, dd, ddd)
    om = np.sqrt(_dot3(a, a))
    if om < 1e-12:
        for c in range(6):
            out[c] = 0.0
        return
    for c in range(6):
        e = (1.0 if c % 3 == 0 else 0.0, 1.0 if c % 3 == 1 else 0.0, 1.0 if c % 3 == 2 else 0.0)
        if c < 3:
            dk = (0.0, 0.0, 0.0)
            dn = e
            dnp = (0.0, 0.0, 0.0)
        else:
            dk = e
            dn = _cross3(e, d)
            dnp = _cross3(e, dd)
        tdn = _dot3(t, dn)
        dt = ((dn[0] - t[0] * tdn) / nn, (dn[1] - t[1] * tdn) / nn, (dn[2] - t[2] * tdn) / nn)
        s = _dot3(dt, npr) + _dot3(t, dnp)
        db = (dnp[0] - dt[0] * tn - t[0] * s, dnp[1] - dt[1] * tn - t[1] * s, dnp[2] - dt[2] * tn - t[2] * s)
        dkt = _cross3(dk, t)
        kdt = _cross3(k, dt)
        f = tdn / (nn * nn)
        da0 = dkt[0] + kdt[0] + db[0] / nn - b[0] * f
        da1 = dkt[1] + kdt[1] + db[1] / nn - b[1] * f
        da2 = dkt[2] + kdt[2] + db[2] / nn - b[2] * f
        out[c] = (a[0] * da0 + a[1] * da1 + a[2] * da2) / om


@_jit_inline
def _combined_strain(w, mixed, mix, r):
    """(x0 .. x5): the strain ``sum_h mix[r, h] strain[mixed[r, h]]`` of
    row r of an actuator point's or wrap node's ``mixed`` and ``mix``
    (its section's, or on field pairs the field's), without an array."""
    x0 = x1 = x2 = x3 = x4 = x5 = 0.0
    for h in range(mixed.shape[1]):
        i = mixed[r, h]
        if i < 0:
            break
        f = mix[r, h]
        S = w.strain
        x0 += f * S[i, 0]
        x1 += f * S[i, 1]
        x2 += f * S[i, 2]
        x3 += f * S[i, 3]
        x4 += f * S[i, 4]
        x5 += f * S[i, 5]
    return x0, x1, x2, x3, x4, x5


@_jit_inline
def _node_strain(w, act, nd, out):
    """out (6,) = the strain at wrap-angle node nd (:func:`_combined_strain`)."""
    out[0], out[1], out[2], out[3], out[4], out[5] = _combined_strain(w, act.node_mixed, act.node_mix, nd)


@_jit_inline
def _wrap_increment(w, act, p, xi):
    """The wrap angle [rad] the tendon turns between point p - 1 (or its
    start) and point p: its nodes' quadrature of :func:`wrap_rate` (xi: a
    scratch (6,))."""
    inc = 0.0
    for nd in range(act.node_ptr[p], act.node_ptr[p + 1]):
        _node_strain(w, act, nd, xi)
        inc += act.node_w[nd] * wrap_rate(xi, act.node_d[nd], act.node_dd[nd], act.node_ddd[nd])
    return inc


@_jit
def tension_factors(w, act):
    """(P,) T(s_p)/u = exp(-mu theta(s_p)) at every actuator quadrature
    point, at the strains of the last forward pass (1 without friction)."""
    out = np.ones(act.joint.shape[0])
    theta = 0.0
    xi = np.empty(6)
    for p in range(act.joint.shape[0]):
        if act.first[p] == 1:
            theta = 0.0
        if act.mu[p] > 0.0:
            theta += _wrap_increment(w, act, p, xi)
            out[p] = np.exp(-act.mu[p] * theta)
    return out


def tendon_tension(model, ws, k, u, s=None):
    """Tension T(s) [N] of tendon k pulled with u [N] at arc lengths s of
    its path (default its termination ``end``), at the strains of ws's last
    forward pass: ``u exp(-mu theta(s))`` (u without sheath friction)."""
    a = model.actuators[k]
    s = np.atleast_1d(np.asarray(a.end if s is None else s, dtype=float))
    if a.friction == 0.0:
        return np.full(s.shape, float(u))
    path = model.path_of_actuator(k)
    theta = np.empty(s.shape)
    for n, si in enumerate(s):
        mixed, mix, d, dd, ddd, wts = _wrap_nodes(model, a, path, a.start, min(max(si, a.start), a.end))
        xi = [sum(f * ws.work.strain[j] for j, f in zip(js, fs) if j >= 0) for js, fs in zip(mixed, mix)]
        theta[n] = sum(wts[i] * wrap_rate(xi[i], d[i], dd[i], ddd[i]) for i in range(len(wts)))
    return u * np.exp(-a.friction * theta)


@_jit_inner
def _add_mixed(m, act, p, scale, wr, out):
    """out[rows of mixed[h]] += scale mix[h] wr[modes] for every section
    point p's strain reads (on field pairs)."""
    for h in range(act.mixed.shape[1]):
        i = act.mixed[p, h]
        if i < 0:
            break
        f = scale * act.mix[p, h]
        iv = m.iv[i]
        for a in range(m.nv[i]):
            out[iv + a] += f * wr[m.modes[i, a]]


@_jit_inline
def _direction(x0, x1, x2, x3, x4, x5, d, dd):
    """(t0, t1, t2, |n|): the unit tangent t = n/|n| of a tendon path at
    offset d (d') on the strain (x0 .. x5), n = nu + kappa x d + d'."""
    n0 = x0 + x4 * d[2] - x5 * d[1] + dd[0]
    n1 = x1 + x5 * d[0] - x3 * d[2] + dd[1]
    n2 = x2 + x3 * d[1] - x4 * d[0] + dd[2]
    nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    return n0 / nn, n1 / nn, n2 / nn, nn


@_jit_inner
def _field_direction(w, act, p):
    """:func:`_direction` at point p on field pairs (:func:`_combined_strain`)."""
    x0, x1, x2, x3, x4, x5 = _combined_strain(w, act.mixed, act.mix, p)
    return _direction(x0, x1, x2, x3, x4, x5, act.d[p], act.dd[p])


@_jit_inline
def _tendon_direction(w, act, p):
    """(t0, t1, t2, |n|): the unit tangent of the tendon path at quadrature
    point p in the cross-section frame (:func:`_direction`), on its
    section's strain or, on field pairs, the field's."""
    if act.mixed[p, 1] >= 0:
        return _field_direction(w, act, p)
    i = act.joint[p]
    S = w.strain
    return _direction(S[i, 0], S[i, 1], S[i, 2], S[i, 3], S[i, 4], S[i, 5], act.d[p], act.dd[p])


@_jit_inline
def _wrench(t0, t1, t2, d, c):
    """c [t; d x t]."""
    return (c * t0, c * t1, c * t2, c * (d[1] * t2 - d[2] * t1), c * (d[2] * t0 - d[0] * t2),
            c * (d[0] * t1 - d[1] * t0))


@_jit_inline
def _own_wrench(w, act, p, c):
    """c [t; d x t] at quadrature point p on its own section's strain."""
    i = act.joint[p]
    S = w.strain
    t0, t1, t2, _ = _direction(S[i, 0], S[i, 1], S[i, 2], S[i, 3], S[i, 4], S[i, 5], act.d[p], act.dd[p])
    return _wrench(t0, t1, t2, act.d[p], c)


@_jit_inner
def _field_wrench(w, act, p, c):
    """c [t; d x t] at quadrature point p on field pairs (the field's strain)."""
    t0, t1, t2, _ = _field_direction(w, act, p)
    return _wrench(t0, t1, t2, act.d[p], c)


@_jit_inline
def _tendon_wrench(w, act, p, c):
    """c [t; d x t] at quadrature point p (t the unit tangent of the tendon
    path in the cross-section frame, :func:`_tendon_direction`)."""
    if act.mixed[p, 1] >= 0:
        return _field_wrench(w, act, p, c)
    return _own_wrench(w, act, p, c)


@_jit
def actuation_pass(m, w, act, coef, out):
    """out += tau_act: the joint-space forces of the distributed actuators,
    coef[p] = sum_k unit[p, k] u_k, at the strains of the last forward pass;
    a tendon with sheath friction at its tension ``exp(-mu theta) u``."""
    theta = 0.0
    xi = np.empty(6)
    for p in range(act.joint.shape[0]):
        c = coef[p]
        if act.first[p] == 1:
            theta = 0.0
        if act.mu[p] > 0.0:
            theta += _wrap_increment(w, act, p, xi)
            c *= np.exp(-act.mu[p] * theta)
        if c == 0.0:
            continue
        if act.mixed[p, 1] >= 0:       # on field pairs: the field's strain, the force on its sections
            _add_mixed(m, act, p, 1.0, _field_wrench(w, act, p, c), out)
            continue                   # (a branch out of the loop, not in its helpers: as fast as before pairs)
        wr = _own_wrench(w, act, p, c)
        i = act.joint[p]
        iv = m.iv[i]
        for a in range(m.nv[i]):
            out[iv + a] += wr[m.modes[i, a]]


def actuation_matrix(tree, ws, act, q, posed=False):
    """B(q) = d tau_act / d u (nv, n_actuators): the generalised actuation
    force per unit input at q, exact (the actuation force is linear in u),
    on ``ws`` (``posed``: its forward pass is at q already). Distributed
    actuators: column k is :func:`actuation_pass` of the unit input e_k;
    a point-moment tendon's column is ``J_body(end)^T [0; d(end) x (-c
    e_x)]``, its follower moment's generalised force. ``act``: the tree's
    :func:`actuator_arrays`."""
    q = np.ascontiguousarray(q, dtype=float)
    if not posed:
        passes.forward_pass(ws.m, ws.w, q, ws.zeros_v, ws.zeros_v, 0)
    Bt = np.zeros((len(tree.actuators), tree.nv))     # rows: contiguous outputs (one compiled layout)
    moments = [k for k, a in enumerate(tree.actuators) if a.tendon_model == "point_moment"]
    for k in range(len(tree.actuators)):
        if k not in moments:
            actuation_pass(ws.m, ws.w, act, np.ascontiguousarray(act.unit[:, k]), Bt[k])
    B = np.ascontiguousarray(Bt.T)
    for k in moments:                 # (point_jacobian runs its own forward pass: after the others)
        a = tree.actuators[k]
        j, x = tree.path_of_actuator(k).locate(np.array([a.end]))
        _, J = point_jacobian(tree, ws, q, int(j[0]), float(x[0]), "body")
        d, _ = a.offset_at(np.array([a.end]))
        B[:, k] = J[3:].T @ np.cross(d[0], -a.force_per_unit_input * np.array([1.0, 0.0, 0.0]))
    return B


@_jit
def actuation_tangent_pass(m, w, act, coef, Kt):
    """Kt -= d tau_act / dq (block diagonal: each section's own strains;
    on field pairs the blocks between the sections a point reads, mix_h
    mix_g times the point's): ``d[t; d x t]/df = [I; hat(d)] (I - t
    t^T)/|n| [I, -hat(d)]`` per point."""
    blk = np.empty((6, 6))
    fac = tension_factors(w, act)
    for p in range(act.joint.shape[0]):
        c = coef[p] * fac[p]
        if c == 0.0:
            continue
        d = act.d[p]
        t0, t1, t2, nn = _tendon_direction(w, act, p)
        t = (t0, t1, t2)
        H = ((0.0, -d[2], d[1]), (d[2], 0.0, -d[0]), (-d[1], d[0], 0.0))
        M3 = np.empty((3, 3))
        for r in range(3):
            for s in range(3):
                M3[r, s] = ((1.0 if r == s else 0.0) - t[r] * t[s]) / nn
        # blk = [I; H] M3 [I, -H]
        MH = np.empty((3, 3))
        HM = np.empty((3, 3))
        for r in range(3):
            for s in range(3):
                acc1 = 0.0
                acc2 = 0.0
                for k in range(3):
                    acc1 += M3[r, k] * H[k][s]
                    acc2 += H[r][k] * M3[k, s]
                MH[r, s] = acc1
                HM[r, s] = acc2
        for r in range(3):
            for s in range(3):
                acc = 0.0
                for k in range(3):
                    acc += H[r][k] * MH[k, s]
                blk[r, s] = M3[r, s]
                blk[r, 3 + s] = -MH[r, s]
                blk[3 + r, s] = HM[r, s]
                blk[3 + r, 3 + s] = -acc
        for h in range(act.mixed.shape[1]):      # the strains the point reads, each by its mix
            i = act.mixed[p, h]
            if i < 0:
                break
            for g in range(act.mixed.shape[1]):
                j = act.mixed[p, g]
                if j < 0:
                    break
                f = c * act.mix[p, h] * act.mix[p, g]
                iv, jv = m.iv[i], m.iv[j]
                for a in range(m.nv[i]):
                    for b in range(m.nv[j]):
                        Kt[iv + a, jv + b] -= f * blk[m.modes[i, a], m.modes[j, b]]
    sheath_tangent_pass(m, w, act, coef, fac, Kt)


@_jit_inline
def sheath_tangent_pass(m, w, act, coef, fac, Kt):
    """Kt -= the friction part of d tau_act/dq: tau_p = coef_p exp(-mu
    theta_p) [t; d x t]_p, and theta_p sums w_n wrap_rate over the nodes n
    before p on its tendon, so ``d tau_p/d xi_n = -mu tau_p (w_n d
    wrap_rate_n/d xi)^T``: a lower-triangular coupling from every section
    the tendon crossed before p to p's section (on field pairs, from the
    sections each node reads to those p's force acts on, by their mixes).
    ``fac``: the :func:`tension_factors`."""
    N = act.node_w.shape[0]
    if N == 0:
        return
    G = np.zeros((N, 6))
    g = np.empty(6)
    xi = np.empty(6)
    for nd in range(N):
        _node_strain(w, act, nd, xi)
        wrap_rate_gradient(xi, act.node_d[nd], act.node_dd[nd], act.node_ddd[nd], g)
        for c in range(6):
            G[nd, c] = act.node_w[nd] * g[c]
    n0 = 0
    for p in range(act.joint.shape[0]):
        if act.first[p] == 1:
            n0 = act.node_ptr[p]
        mu = act.mu[p]
        c = coef[p] * fac[p]
        if mu == 0.0 or c == 0.0:
            continue
        wr = _tendon_wrench(w, act, p, c)
        for h in range(act.mixed.shape[1]):            # the strains p's force acts on, each by its mix
            i = act.mixed[p, h]
            if i < 0:
                break
            iv = m.iv[i]
            for nd in range(n0, act.node_ptr[p + 1]):
                for g_ in range(act.node_mixed.shape[1]):     # the strains node nd reads
                    j = act.node_mixed[nd, g_]
                    if j < 0:
                        break
                    f = mu * act.mix[p, h] * act.node_mix[nd, g_]
                    jv = m.iv[j]
                    for a in range(m.nv[i]):
                        x = f * wr[m.modes[i, a]]
                        for b in range(m.nv[j]):
                            Kt[iv + a, jv + b] += x * G[nd, m.modes[j, b]]
