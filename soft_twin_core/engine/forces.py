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
  :func:`actuation_pass` the compiled sum. Tendons of the point-moment model
  (slides part C, model (b)) are follower point moments at their
  termination instead.
"""

from collections import namedtuple
from dataclasses import replace

import numpy as np

from soft_twin_core.engine.algorithms import point_jacobian
from soft_twin_core.engine.kernels import passes
from soft_twin_core.engine.kernels.data import LoadArrays
from soft_twin_core.engine.kernels.spatial import _jit, _jit_inline
from soft_twin_core.engine.loads import Loads, actuator_point_loads

ActuatorArrays = namedtuple("ActuatorArrays", [
    "joint",      # (P,) soft joint of each tendon quadrature point
    "d", "dd",    # (P, 3) offset d(s) and d'(s) in the cross-section frame [m, -]
    "unit",       # (P, n_actuators): coefficient per unit input (-c w: m per N or m^3 per Pa... see module)
])


def _gauss_on_path(model, path, start, end):
    """(joint, x, s, w) Gauss points of each section of ``path`` over its
    overlap with [start, end] (the section's own point count)."""
    js, xs, ss, ws = [], [], [], []
    for k, j in enumerate(path.joints):
        a = max(path.s_starts[k], start)
        b = min(path.s_starts[k] + path.lengths[k], end)
        if b <= a:
            continue
        xg, wg = np.polynomial.legendre.leggauss(model.joints[j].section.quadrature_points)
        s = 0.5 * (a + b) + 0.5 * (b - a) * xg
        js += [j] * len(xg)
        xs.append(s - path.s_starts[k])
        ss.append(s)
        ws.append(0.5 * (b - a) * wg)
    if not js:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0)
    return np.array(js, np.int64), np.concatenate(xs), np.concatenate(ss), np.concatenate(ws)


def actuator_arrays(model):
    """Quadrature geometry of the model's distributed actuators (tendon model
    "distributed") on their path."""
    J, D, DD, U = [], [], [], []
    na = len(model.actuators)
    for k, a in enumerate(model.actuators):
        if a.tendon_model == "point_moment":
            continue
        j, _, s, w = _gauss_on_path(model, model.path_of_actuator(k), a.start, a.end)
        d, dd = a.offset_at(s)
        unit = np.zeros((len(s), na))
        unit[:, k] = -a.force_per_unit_input * w
        J.append(j)
        D.append(d)
        DD.append(dd)
        U.append(unit)
    if not J:
        return ActuatorArrays(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, na)))
    return ActuatorArrays(np.concatenate(J), np.ascontiguousarray(np.concatenate(D)),
                          np.ascontiguousarray(np.concatenate(DD)), np.ascontiguousarray(np.concatenate(U)))


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
        return LoadArrays(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 6)), np.zeros(0, np.bool_))
    if len(lds) == 1:
        return lds[0]
    return LoadArrays(np.concatenate([ld.joint for ld in lds]), np.ascontiguousarray(np.concatenate([ld.x for ld in lds])),
                      np.ascontiguousarray(np.concatenate([ld.wrench for ld in lds])),
                      np.concatenate([ld.world for ld in lds]))


def gravity_of(model, loads=None):
    """Gravity vector [m/s^2] (world) the loads switch on or scale."""
    grav = True if loads is None else loads.gravity
    scale = (1.0 if grav else 0.0) if isinstance(grav, bool) else float(grav)
    return scale * np.asarray(model.gravity, dtype=float)


@_jit_inline
def actuation_pass(m, w, act, coef, out):
    """out += tau_act: the joint-space forces of the distributed actuators,
    coef[p] = sum_k unit[p, k] u_k, at the strains of the last forward pass."""
    for p in range(act.joint.shape[0]):
        c = coef[p]
        if c == 0.0:
            continue
        i = act.joint[p]
        d = act.d[p]
        xi = w.strain[i]
        t0 = xi[0] + xi[4] * d[2] - xi[5] * d[1] + act.dd[p, 0]
        t1 = xi[1] + xi[5] * d[0] - xi[3] * d[2] + act.dd[p, 1]
        t2 = xi[2] + xi[3] * d[1] - xi[4] * d[0] + act.dd[p, 2]
        nt = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
        t0, t1, t2 = t0 / nt, t1 / nt, t2 / nt
        wr = (c * t0, c * t1, c * t2, c * (d[1] * t2 - d[2] * t1), c * (d[2] * t0 - d[0] * t2),
              c * (d[0] * t1 - d[1] * t0))
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
    B = np.zeros((tree.nv, len(tree.actuators)))
    moments = [k for k, a in enumerate(tree.actuators) if a.tendon_model == "point_moment"]
    for k in range(len(tree.actuators)):
        if k not in moments:
            actuation_pass(ws.m, ws.w, act, np.ascontiguousarray(act.unit[:, k]), B[:, k])
    for k in moments:                 # (point_jacobian runs its own forward pass: after the others)
        a = tree.actuators[k]
        j, x = tree.path_of_actuator(k).locate(np.array([a.end]))
        _, J = point_jacobian(tree, ws, q, int(j[0]), float(x[0]), "body")
        d, _ = a.offset_at(np.array([a.end]))
        B[:, k] = J[3:].T @ np.cross(d[0], -a.force_per_unit_input * np.array([1.0, 0.0, 0.0]))
    return B


@_jit
def actuation_tangent_pass(m, w, act, coef, Kt):
    """Kt -= d tau_act / dq (block diagonal: each section's own strains):
    ``d[t; d x t]/df = [I; hat(d)] (I - t t^T)/|n| [I, -hat(d)]`` per point."""
    blk = np.empty((6, 6))
    for p in range(act.joint.shape[0]):
        c = coef[p]
        if c == 0.0:
            continue
        i = act.joint[p]
        d = act.d[p]
        xi = w.strain[i]
        n0 = xi[0] + xi[4] * d[2] - xi[5] * d[1] + act.dd[p, 0]
        n1 = xi[1] + xi[5] * d[0] - xi[3] * d[2] + act.dd[p, 1]
        n2 = xi[2] + xi[3] * d[1] - xi[4] * d[0] + act.dd[p, 2]
        nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        t = (n0 / nn, n1 / nn, n2 / nn)
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
        iv = m.iv[i]
        for a in range(m.nv[i]):
            for b in range(m.nv[i]):
                Kt[iv + a, iv + b] -= c * blk[m.modes[i, a], m.modes[i, b]]
