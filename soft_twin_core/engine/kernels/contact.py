"""Compiled contact law (the formulas: :mod:`soft_twin_core.engine.contact`,
whose array functions call these): per point, the obstacles' signed
distance with its gradient and Hessian, the penalty force and its stored
energy, the step's mean force (discrete gradient), regularised Coulomb
friction; and the passes that list the contacts of a configuration
(statics) or of a time step (dynamics) into preallocated arrays.

Obstacles are :class:`ObstacleArrays` (one row per obstacle; NaN stiffness
or smoothing: the member's default)."""

from functools import lru_cache

import numba as nb
import numpy as np
from numba.experimental import structref

from soft_twin_core.engine.kernels.data import ArraysRef, ArraysType, declare
from soft_twin_core.engine.kernels.spatial import _jit, _jit_inline, _jit_inner

PLANE, SPHERE, CAPSULE, BOX, MESH, TUBE = 0, 1, 2, 3, 4, 5
KIND_CODES = {"plane": PLANE, "sphere": SPHERE, "capsule": CAPSULE, "box": BOX, "mesh": MESH, "tube": TUBE}

OBSTACLE_FIELDS = (
    "kind",        # (O,) PLANE, SPHERE, CAPSULE or BOX
    "a", "b",      # (O, 3) engine.contact.Obstacle.a and .b (zeros where unused)
    "radius",      # (O,) [m]
    "rotation",    # (O, 3, 3) a box's or mesh's axes (identity otherwise)
    "half",        # (O, 3) a box's half sizes [m]
    "stiffness",   # (O,) [N/m^2], NaN: the member's Young's modulus
    "smoothing",   # (O,) [m], NaN: a tenth of the member's radius
    "damping",     # (O,) Hunt-Crossley alpha [s/m]
    "friction",    # (O,) Coulomb mu
    "stiction",    # (O,) the stiction velocity [m/s]
    "torsion",     # (O,) torsional (spin) friction mu_t [m]: the largest moment about the normal is mu_t F_n
    "tri",         # (T, 3, 3) every mesh's triangles, in its axes about its a, outward (counter-clockwise)
    "tri_start",   # (O + 1,) obstacle o's triangles: tri[tri_start[o]:tri_start[o + 1]]
    "normals",     # (T, 7, 3) each triangle's unit normal, its edges' and vertices' pseudonormals (mesh_normals)
    "box",         # (N, 2, 3) every mesh's bounding-box tree (mesh_tree): each node's box [lo, hi] in its axes
    "node",        # (N, 4) int: [left, right, first, end], children -1 at a leaf: tri[first:end] (absolute)
    "node_start",  # (O + 1,) obstacle o's nodes: node_start[o] its tree's root (mesh obstacles)
    "body",        # (O,) the joint whose output frame carries the obstacle (a link's collision shape), -1: the world
    "path",        # (N, 3) every tube's centre line, in its axes about its a
    "path_start",  # (O + 1,) obstacle o's centre line: path[path_start[o]:path_start[o + 1]]
)


@structref.register
class ObstacleArraysType(ArraysType):
    pass


class ObstacleArrays(ArraysRef):
    """The obstacles' arrays (:data:`OBSTACLE_FIELDS`) as the kernels take them."""
    FIELDS = OBSTACLE_FIELDS


declare(ObstacleArrays, ObstacleArraysType, OBSTACLE_FIELDS)


@nb.njit(cache=True)
def _make_obstacle_ref(kind, a, b, radius, rotation, half, stiffness, smoothing, damping, friction, stiction,
                       torsion, tri, tri_start, normals, box, node, node_start, body, path, path_start):
    return ObstacleArrays(kind, a, b, radius, rotation, half, stiffness, smoothing, damping, friction, stiction,
                          torsion, tri, tri_start, normals, box, node, node_start, body, path, path_start)


ObstacleArrays.make = _make_obstacle_ref


MESH_LEAF = 4       # triangles in a leaf of a mesh's bounding-box tree


def obstacle_arrays(obstacles, leaf=MESH_LEAF):
    """:class:`ObstacleArrays` of a sequence of engine.contact.Obstacle
    (immutable, compared by identity: the arrays of the last few tuples
    are kept); ``leaf``: the most triangles in a leaf of a mesh's tree."""
    return _obstacle_arrays(tuple(obstacles), leaf)


def mesh_tree(tri, leaf=MESH_LEAF):
    """A bounding-box tree of a mesh's triangles (T, 3, 3): (order (T,) the
    triangles in the tree's order, each leaf's contiguous; box (N, 2, 3)
    each node's axis-aligned box [lo, hi]; node (N, 4) int [left, right,
    first, end], the children -1 at a leaf, whose triangles are
    tri[order][first:end]). Node 0 is the root; each node splits its
    triangles at the median of their centroids along its longest extent,
    down to ``leaf`` triangles."""
    tri = np.asarray(tri, dtype=float)
    cen = tri.mean(axis=1)
    order = np.arange(len(tri))
    boxes, nodes = [], []

    def build(lo, hi):                    # the node of order[lo:hi]; returns its index
        k = len(nodes)
        pts = tri[order[lo:hi]].reshape(-1, 3)
        boxes.append((pts.min(axis=0), pts.max(axis=0)))
        nodes.append([-1, -1, lo, hi])
        if hi - lo > leaf:
            c = cen[order[lo:hi]]
            axis = int(np.argmax(np.ptp(c, axis=0)))
            order[lo:hi] = order[lo:hi][np.argsort(c[:, axis], kind="stable")]
            mid = (lo + hi) // 2
            nodes[k][0] = build(lo, mid)
            nodes[k][1] = build(mid, hi)
        return k
    if len(tri):
        build(0, len(tri))
    return order, np.array(boxes, dtype=float).reshape(-1, 2, 3), np.array(nodes, dtype=np.int64).reshape(-1, 4)


@lru_cache(maxsize=16)
def _obstacle_arrays(obstacles, leaf):
    O = len(obstacles)
    kind = np.array([KIND_CODES[ob.kind] for ob in obstacles], np.int64)
    a, b, half = np.zeros((O, 3)), np.zeros((O, 3)), np.zeros((O, 3))
    rot = np.tile(np.eye(3), (O, 1, 1))
    nan = float("nan")
    tris, start, normals = [np.zeros((0, 3, 3))], np.zeros(O + 1, np.int64), [np.zeros((0, 7, 3))]
    boxes, nodes, nstart = [np.zeros((0, 2, 3))], [np.zeros((0, 4), np.int64)], np.zeros(O + 1, np.int64)
    paths, pstart = [np.zeros((0, 3))], np.zeros(O + 1, np.int64)
    for o, ob in enumerate(obstacles):
        a[o] = ob.a
        if ob.b is not None:
            b[o] = ob.b
        if ob.kind in ("box", "mesh", "tube"):
            rot[o] = ob.rotation
        if ob.kind == "tube":
            paths.append(ob.path)
        pstart[o + 1] = pstart[o] + (len(ob.path) if ob.kind == "tube" else 0)
        if ob.kind == "box":
            half[o] = ob.half_size
        if ob.kind == "mesh":
            order, box, node = mesh_tree(ob.triangles, leaf)
            tris.append(ob.triangles[order])
            normals.append(mesh_normals(ob.triangles)[order])
            node[:, :2] = np.where(node[:, :2] >= 0, node[:, :2] + nstart[o], -1)     # absolute indices
            node[:, 2:] += start[o]
            boxes.append(box)
            nodes.append(node)
        nstart[o + 1] = nstart[o] + (len(nodes[-1]) if ob.kind == "mesh" else 0)
        start[o + 1] = start[o] + (len(ob.triangles) if ob.kind == "mesh" else 0)
    col = (lambda f: np.array([f(ob) for ob in obstacles], dtype=float))
    return ObstacleArrays.of(kind, a, b, col(lambda ob: ob.radius), rot, half,
                             col(lambda ob: nan if ob.stiffness is None else ob.stiffness),
                             col(lambda ob: nan if ob.smoothing is None else ob.smoothing),
                             col(lambda ob: ob.damping), col(lambda ob: ob.friction),
                             col(lambda ob: ob.stiction_velocity), col(lambda ob: ob.torsional_friction),
                             np.ascontiguousarray(np.concatenate(tris)), start, np.ascontiguousarray(np.concatenate(normals)),
                             np.ascontiguousarray(np.concatenate(boxes)), np.ascontiguousarray(np.concatenate(nodes)),
                             nstart,
                             np.array([ob.body for ob in obstacles], np.int64),
                             np.ascontiguousarray(np.concatenate(paths)), pstart)


def mesh_normals(tri):
    """(T, 7, 3): for each triangle (T, 3, 3) of a closed mesh turned
    outward, its unit normal, then its edges' (AB, AC, BC) and its
    vertices' (A, B, C) angle-weighted pseudonormals (Baerentzen and
    Aanaes, IEEE TVCG 11(3), 2005): an edge's, the sum of its two faces'
    normals; a vertex's, the sum of its faces' normals each weighted by the
    face's angle there. The side of a point p is the sign of (p - c) . N
    for c the nearest point of the surface and N the pseudonormal of the
    feature c lies on, for any closed mesh, convex or not."""
    tri = np.asarray(tri, dtype=float)
    T = len(tri)
    out = np.zeros((T, 7, 3))
    if T == 0:
        return out
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    out[:, 0] = nrm
    # the vertices by position (one mesh's triangles share them exactly)
    _, vid = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
    vid = vid.reshape(T, 3)
    at_vertex = np.zeros((vid.max() + 1, 3))
    for k in range(3):
        e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
        cos = np.einsum("ij,ij->i", e1, e2) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        np.add.at(at_vertex, vid[:, k], np.arccos(np.clip(cos, -1.0, 1.0))[:, None] * nrm)
    pairs = ((0, 1), (0, 2), (1, 2))
    edge_key = (lambda t, a, b: (min(vid[t, a], vid[t, b]), max(vid[t, a], vid[t, b])))
    at_edge = {}
    for t in range(T):
        for a, b in pairs:
            at_edge[edge_key(t, a, b)] = at_edge.get(edge_key(t, a, b), 0.0) + nrm[t]
    for t in range(T):
        for k, (a, b) in enumerate(pairs):
            out[t, 1 + k] = at_edge[edge_key(t, a, b)]
        out[t, 4:] = at_vertex[vid[t]]
    size = np.linalg.norm(out, axis=2, keepdims=True)
    return out / np.where(size > 0, size, 1.0)


def posable(obs):
    """A copy of ``obs`` whose poses (a, b, rotation) :func:`pose_obstacles`
    may overwrite (the shapes and laws shared)."""
    arrays = list(obs.__dict__["arrays"])
    for name in ("a", "b", "rotation"):
        k = OBSTACLE_FIELDS.index(name)
        arrays[k] = arrays[k].copy()
    return ObstacleArrays.of(*arrays)


@_jit
def pose_obstacles(w, local, out):
    """The obstacles carried by bodies (``local.body >= 0``: a, b, rotation
    in the body's output frame) posed in the world from the workspace's
    poses (after a forward pass) into ``out`` (:func:`posable`): ``a`` and a
    capsule's ``b`` as points, the rotation composed."""
    for o in range(local.kind.shape[0]):
        j = local.body[o]
        if j < 0:
            continue
        G = w.g_out[j]
        for r in range(3):
            out.a[o, r] = G[r, 3]
            out.b[o, r] = G[r, 3] if local.kind[o] == CAPSULE else 0.0
            for c in range(3):
                out.a[o, r] += G[r, c] * local.a[o, c]
                if local.kind[o] == CAPSULE:
                    out.b[o, r] += G[r, c] * local.b[o, c]
                acc = 0.0
                for k in range(3):
                    acc += G[r, k] * local.rotation[o, k, c]
                out.rotation[o, r, c] = acc


# --- the law, per point ---------------------------------------------------------

@_jit_inline
def penalty(delta, k, eps):
    """(f, df/ddelta) [N/m, N/m^2] at penetration delta: 0 outside,
    k delta^2 / (2 eps) up to eps, then k (delta - eps/2) (C1)."""
    if delta <= 0.0:
        return 0.0, 0.0
    if delta < eps:
        return 0.5 * k * delta * delta / eps, k * delta / eps
    return k * (delta - 0.5 * eps), k


@_jit_inline
def penalty_potential(delta, k, eps):
    """Phi(delta) = int_0^delta f [N]."""
    if delta <= 0.0:
        return 0.0
    if delta < eps:
        return k * delta ** 3 / (6.0 * eps)
    return k * (0.5 * delta * delta - 0.5 * eps * delta + eps * eps / 6.0)


@_jit_inline
def mean_force(d0, d1, k, eps):
    """(fbar, d fbar/d d1): (Phi(d1) - Phi(d0)) / (d1 - d0), in closed
    form where both ends share a branch of the law."""
    if d0 <= 0.0 and d1 <= 0.0:
        return 0.0, 0.0
    if 0.0 < d0 < eps and 0.0 < d1 < eps:
        return k * (d0 * d0 + d0 * d1 + d1 * d1) / (6.0 * eps), k * (d0 + 2.0 * d1) / (6.0 * eps)
    if d0 >= eps and d1 >= eps:
        return 0.5 * k * (d0 + d1 - eps), 0.5 * k
    dd = d1 - d0
    if dd == 0.0:
        dd = 1.0
    q = (penalty_potential(d1, k, eps) - penalty_potential(d0, k, eps)) / dd
    f1, _ = penalty(d1, k, eps)
    return q, (f1 - q) / dd


@_jit_inline
def bounding_sphere(obs, o):
    """(cx, cy, cz, R): a sphere holding obstacle o (a sphere's own; a
    capsule's centre and half length plus radius); R infinite for the other
    kinds. The broad phase before :func:`distance` (about a microsecond) on
    every (point, obstacle) pair: a point p of radius r with ``|p - c| >= R
    + r`` cannot touch (the surface distance is at least ``|p - c| - R``).
    Read once per obstacle: a structure's field costs more than the test."""
    kind = obs.kind[o]
    a, b = obs.a, obs.b
    if kind == SPHERE:
        return a[o, 0], a[o, 1], a[o, 2], obs.radius[o]
    if kind == CAPSULE:
        ax, ay, az = b[o, 0] - a[o, 0], b[o, 1] - a[o, 1], b[o, 2] - a[o, 2]
        return (0.5 * (a[o, 0] + b[o, 0]), 0.5 * (a[o, 1] + b[o, 1]), 0.5 * (a[o, 2] + b[o, 2]),
                0.5 * np.sqrt(ax * ax + ay * ay + az * az) + obs.radius[o])
    if kind == MESH and obs.node_start[o + 1] > obs.node_start[o]:      # its tree's root box, turned
        B = obs.box[obs.node_start[o]]
        R = obs.rotation[o]
        c = np.empty(3)
        h2 = 0.0
        for r in range(3):
            c[r] = 0.5 * (B[0, r] + B[1, r])
            h2 += 0.25 * (B[1, r] - B[0, r]) ** 2
        return (a[o, 0] + R[0, 0] * c[0] + R[0, 1] * c[1] + R[0, 2] * c[2],
                a[o, 1] + R[1, 0] * c[0] + R[1, 1] * c[1] + R[1, 2] * c[2],
                a[o, 2] + R[2, 0] * c[0] + R[2, 1] * c[1] + R[2, 2] * c[2], np.sqrt(h2))
    return 0.0, 0.0, 0.0, np.inf


@_jit_inline
def far_from(bound, p, i, r):
    """True when point p[i] of radius r [m] lies outside the obstacle's
    :func:`bounding_sphere` by more than r: it cannot touch."""
    cx, cy, cz, R = bound
    dx, dy, dz = p[i, 0] - cx, p[i, 1] - cy, p[i, 2] - cz
    return dx * dx + dy * dy + dz * dz >= (R + r) * (R + r)


@_jit_inner
def distance(obs, o, p, n, H):
    """Signed distance [m] of point p from obstacle o's surface (> 0
    outside); n (3,) receives its gradient (the outward normal), H (3, 3)
    its Hessian."""
    kind = obs.kind[o]
    for r in range(3):
        for c in range(3):
            H[r, c] = 0.0
    if kind == PLANE:
        d = 0.0
        for r in range(3):
            n[r] = obs.b[o, r]
            d += (p[r] - obs.a[o, r]) * obs.b[o, r]
        return d
    if kind == BOX:
        return _box_distance(obs, o, p, n, H)
    if kind == MESH:
        return _mesh_distance(obs, o, p, n, H)
    if kind == TUBE:
        return _tube_distance(obs, o, p, n, H)
    c = np.empty(3)
    axis = np.zeros(3)
    if kind == SPHERE:
        for r in range(3):
            c[r] = obs.a[o, r]
    else:
        ab = obs.b[o] - obs.a[o]
        L2 = ab[0] * ab[0] + ab[1] * ab[1] + ab[2] * ab[2]
        t = ((p[0] - obs.a[o, 0]) * ab[0] + (p[1] - obs.a[o, 1]) * ab[1] + (p[2] - obs.a[o, 2]) * ab[2]) / L2
        t = min(max(t, 0.0), 1.0)
        for r in range(3):
            c[r] = obs.a[o, r] + t * ab[r]
        if 0.0 < t < 1.0:
            axis = ab / np.sqrt(L2)
    v = p - c
    dist = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    safe = max(dist, 1e-300)
    for r in range(3):
        n[r] = v[r] / safe
    for r in range(3):
        for s in range(3):
            H[r, s] = ((1.0 if r == s else 0.0) - n[r] * n[s] - axis[r] * axis[s]) / safe
    return dist - obs.radius[o]


@_jit_inline
def _box_distance(obs, o, p, n, H):
    """A box's signed distance: in its axes, with e = |p| - h per axis,
    outside ``|max(e, 0)|`` (to a face, an edge or a corner: Hessian
    ``(A - n n^T) / d``, A the projector on the axes where e > 0), inside
    ``max(e)`` (to the nearest face: Hessian 0)."""
    R = obs.rotation[o]
    loc = np.zeros(3)
    for c in range(3):
        for r in range(3):
            loc[c] += (p[r] - obs.a[o, r]) * R[r, c]
    e = np.abs(loc) - obs.half[o]
    sgn = np.where(loc < 0.0, -1.0, 1.0)
    out_e = np.maximum(e, 0.0)
    d_out = np.sqrt(out_e[0] * out_e[0] + out_e[1] * out_e[1] + out_e[2] * out_e[2])
    n_loc = np.zeros(3)
    if d_out > 0.0:
        for r in range(3):
            n_loc[r] = sgn[r] * out_e[r] / d_out
        d = d_out
    else:
        k = int(np.argmax(e))
        n_loc[k] = sgn[k]
        d = e[k]
    for r in range(3):
        n[r] = R[r, 0] * n_loc[0] + R[r, 1] * n_loc[1] + R[r, 2] * n_loc[2]
    if d_out > 0.0:          # H = R Hl R^T
        for r in range(3):
            for s in range(3):
                acc = 0.0
                for a in range(3):
                    acc += R[r, a] * R[s, a] * (1.0 if e[a] > 0.0 else 0.0)
                H[r, s] = (acc - n[r] * n[s]) / d_out
    return d


@_jit_inline
def _to_world(R, n_loc, Hl, n, H):
    """n = R n_loc, H = R Hl R^T: a gradient and Hessian from an obstacle's axes to the world's."""
    for r in range(3):
        n[r] = R[r, 0] * n_loc[0] + R[r, 1] * n_loc[1] + R[r, 2] * n_loc[2]
        for s in range(3):
            acc = 0.0
            for a in range(3):
                for b in range(3):
                    acc += R[r, a] * Hl[a, b] * R[s, b]
            H[r, s] = acc


@_jit_inline
def _tube_distance(obs, o, p, n, H):
    """A tube's signed distance: the free space is inside, within ``radius``
    of its centre line (a polyline, open at both ends), so ``d = radius -
    |p - c|`` with c the line's nearest point (its nearest segment's);
    gradient ``-(p - c) / |p - c|`` (towards the centre line), Hessian
    ``-(I - n n^T - t t^T) / |p - c|`` (t the segment's direction inside
    its span). A point beyond either open end touches nothing (1e30)."""
    R = obs.rotation[o]
    loc = np.zeros(3)
    for c in range(3):
        for r in range(3):
            loc[c] += (p[r] - obs.a[o, r]) * R[r, c]
    i0, i1 = obs.path_start[o], obs.path_start[o + 1]
    best, bt, bk, braw = np.inf, 0.0, -1, 0.0
    for k in range(i0, i1 - 1):
        A, B = obs.path[k], obs.path[k + 1]
        ab = B - A
        raw = np.dot(loc - A, ab) / np.dot(ab, ab)
        t = min(max(raw, 0.0), 1.0)
        v = loc - (A + t * ab)
        dd = np.dot(v, v)
        if dd < best:
            best, bt, bk, braw = dd, t, k, raw
    if (bk == i0 and braw < 0.0) or (bk == i1 - 2 and braw > 1.0):
        return 1e30                         # nearest to an open end, from beyond it
    A, B = obs.path[bk], obs.path[bk + 1]
    ab = B - A
    v = loc - (A + bt * ab)
    dist = max(np.sqrt(best), 1e-300)
    u = v / dist
    axis = np.zeros(3)
    if 0.0 < bt < 1.0:
        axis = ab / np.sqrt(np.dot(ab, ab))
    Hl = np.zeros((3, 3))
    for r in range(3):
        for s in range(3):
            Hl[r, s] = -((1.0 if r == s else 0.0) - u[r] * u[s] - axis[r] * axis[s]) / dist
    _to_world(R, -u, Hl, n, H)
    return obs.radius[o] - dist


@_jit_inline
def closest_on_triangle(p, A, B, C, out):
    """The point of triangle ABC nearest p into ``out`` (3,); returns the
    feature it lies on: 0 the face, 1-3 an edge (AB, AC, BC), 4 a vertex
    (Ericson, Real-Time Collision Detection, 2005, section 5.1.5: the
    Voronoi regions of the vertices, then the edges, else the face)."""
    ab, ac, ap = B - A, C - A, p - A
    d1, d2 = np.dot(ab, ap), np.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        out[:] = A
        return 4
    bp = p - B
    d3, d4 = np.dot(ab, bp), np.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        out[:] = B
        return 4
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        out[:] = A + d1 / (d1 - d3) * ab
        return 1
    cp = p - C
    d5, d6 = np.dot(ab, cp), np.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        out[:] = C
        return 4
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        out[:] = A + d2 / (d2 - d6) * ac
        return 2
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        out[:] = B + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (C - B)
        return 3
    den = 1.0 / (va + vb + vc)
    out[:] = A + ab * (vb * den) + ac * (vc * den)
    return 0


@_jit_inline
def _box_gap2(p, B):
    """The squared distance from p to the box B = [lo, hi] (0 inside)."""
    out = 0.0
    for r in range(3):
        e = max(B[0, r] - p[r], p[r] - B[1, r], 0.0)
        out += e * e
    return out


@_jit_inline
def _mesh_distance(obs, o, p, n, H):
    """A closed mesh's signed distance, convex or not (its triangles
    outward): the distance to the nearest point c of the nearest triangle
    (found by the mesh's box tree, :func:`mesh_tree`: O(log T) a point),
    its sign the side of the pseudonormal of the feature c lies on
    (:func:`mesh_normals`). Gradient: the face's normal on a face, else the
    unit vector from c (signed: outward); Hessian 0 on a face, from an edge
    ``(I - n n^T - e e^T) / d`` (e along the edge), from a vertex
    ``(I - n n^T) / d`` (d signed, negative inside). In the mesh's axes
    about a."""
    R = obs.rotation[o]
    loc = np.zeros(3)
    for c in range(3):
        for r in range(3):
            loc[c] += (p[r] - obs.a[o, r]) * R[r, c]
    c, q = np.empty(3), np.empty(3)
    d2, feat, tbest = np.inf, 0, obs.tri_start[o]
    # the nearest triangle by the mesh's box tree: nearer child first, boxes farther than the best skipped
    stack = np.empty(64, np.int64)
    stack[0], top = obs.node_start[o], 0
    while top >= 0:
        k = stack[top]
        top -= 1
        if _box_gap2(loc, obs.box[k]) >= d2:
            continue
        left, right = obs.node[k, 0], obs.node[k, 1]
        if left < 0:
            for t in range(obs.node[k, 2], obs.node[k, 3]):
                T = obs.tri[t]
                f = closest_on_triangle(loc, T[0], T[1], T[2], q)
                v = loc - q
                dd = np.dot(v, v)
                if dd < d2:
                    d2, feat, tbest = dd, f, t
                    c[:] = q
            continue
        near, far = left, right
        if _box_gap2(loc, obs.box[right]) < _box_gap2(loc, obs.box[left]):
            near, far = right, left
        stack[top + 1], stack[top + 2] = far, near
        top += 2
    T = obs.tri[tbest]
    k = feat
    if feat == 4:               # which vertex (closest_on_triangle copies it)
        k = 4
        for j in range(1, 3):
            if np.dot(c - T[j], c - T[j]) < np.dot(c - T[k - 4], c - T[k - 4]):
                k = 4 + j
    v = loc - c
    dist = np.sqrt(d2)
    side = 1.0 if np.dot(v, obs.normals[tbest, k]) >= 0.0 else -1.0
    Hl = np.zeros((3, 3))
    n_loc = obs.normals[tbest, 0].copy()
    d = side * dist
    if feat != 0 and dist > 1e-300:
        n_loc = side * v / dist
        e = np.zeros(3)
        if feat < 4:
            e = (T[1] - T[0]) if feat == 1 else ((T[2] - T[0]) if feat == 2 else (T[2] - T[1]))
            e /= np.sqrt(np.dot(e, e))
        for r in range(3):
            for s in range(3):
                Hl[r, s] = ((1.0 if r == s else 0.0) - n_loc[r] * n_loc[s] - e[r] * e[s]) / d
    _to_world(R, n_loc, Hl, n, H)
    return d


@_jit_inline
def friction(fn, vt, mu, v_s, F, dF):
    """Regularised Coulomb friction: F (3,) = -mu fn vt / sqrt(|vt|^2 +
    v_s^2), dF (3, 3) = dF/dvt."""
    s2 = vt[0] * vt[0] + vt[1] * vt[1] + vt[2] * vt[2] + v_s * v_s
    c = mu * fn / np.sqrt(s2)
    for r in range(3):
        F[r] = -c * vt[r]
        for q in range(3):
            dF[r, q] = -c * ((1.0 if r == q else 0.0) - vt[r] * vt[q] / s2)


@_jit_inline
def spin_friction(fn, spin, mu_t, v_s):
    """Regularised torsional friction of a contact patch: the moment about
    the normal ``m = -mu_t fn s / sqrt(s^2 + v_s^2)``, ``s = mu_t spin``
    (spin [rad/s] about the normal; s: the slip of a rim at mu_t), and
    dm/dspin. Returns (m, dm)."""
    s = mu_t * spin
    d2 = s * s + v_s * v_s
    d = np.sqrt(d2)
    return -mu_t * fn * s / d, -mu_t * mu_t * fn * v_s * v_s / (d2 * d)


@_jit_inline
def rotation_rate(R0, R1, h, out):
    """out (3,) [rad/s]: the mean angular velocity, world axes, that turns
    R0 into R1 in h: the rotation vector of R1 R0^T over h (angles < pi)."""
    Q = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            Q[r, c] = R1[r, 0] * R0[c, 0] + R1[r, 1] * R0[c, 1] + R1[r, 2] * R0[c, 2]
    vx, vy, vz = 0.5 * (Q[2, 1] - Q[1, 2]), 0.5 * (Q[0, 2] - Q[2, 0]), 0.5 * (Q[1, 0] - Q[0, 1])
    sn = np.sqrt(vx * vx + vy * vy + vz * vz)
    cs = 0.5 * (Q[0, 0] + Q[1, 1] + Q[2, 2] - 1.0)
    f = 1.0 + sn * sn / 6.0 if sn < 1e-6 and cs > 0.0 else np.arctan2(sn, cs) / sn
    out[0], out[1], out[2] = f * vx / h, f * vy / h, f * vz / h


@_jit_inner
def transition_fraction(v, d, vs):
    """The fraction in (0, 1] of an update that changes a contact's slip v
    (3,) by d (3,) to take (:func:`soft_twin_core.engine.contact.transition_step`):
    a sticking contact (|v| < vs) set sliding stops at |v + a d| = vs; a
    sliding one whose slip would reverse stops where its path passes
    closest to zero; else 1."""
    dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    if dd == 0.0:
        return 1.0
    vd = v[0] * d[0] + v[1] * d[1] + v[2] * d[2]
    x0 = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    x1 = np.sqrt((v[0] + d[0]) ** 2 + (v[1] + d[1]) ** 2 + (v[2] + d[2]) ** 2)
    if x0 < vs and x1 > 2.0 * vs:
        a = (-vd + np.sqrt(max(vd * vd - dd * (x0 * x0 - 4.0 * vs * vs), 0.0))) / dd
        return max(a, 1e-3)
    if x0 > vs and x1 > vs and x0 * x0 + vd < 0.0:
        return max(-vd / dd, 1e-3)
    return 1.0


@_jit
def transition_fractions(slip, dslip, vs):
    """The smallest :func:`transition_fraction` over contacts (c, 3)."""
    alpha = 1.0
    for k in range(slip.shape[0]):
        alpha = min(alpha, transition_fraction(slip[k], dslip[k], vs[k]))
    return alpha


# --- the passes ---------------------------------------------------------------

@_jit
def rest_contacts(radius, modulus, weight, allowed, obs, p, idx, ob_of, n_out, gap, F, dF):
    """Statics: every ``allowed`` (P, O) (point, obstacle) pair pressed in
    at positions p (P, 3), obstacle-major; fills the outputs (sized P O)
    and returns their count: force F = w f n and dF/dp = w (-f' n n^T + f H)."""
    n = np.empty(3)
    H = np.empty((3, 3))
    c = 0
    for o in range(obs.kind.shape[0]):
        bound = bounding_sphere(obs, o)
        for i in range(p.shape[0]):
            if not allowed[i, o] or far_from(bound, p, i, radius[i]):
                continue
            d = distance(obs, o, p[i], n, H)
            delta = radius[i] - d
            if delta <= 0.0:
                continue
            k = modulus[i] if np.isnan(obs.stiffness[o]) else obs.stiffness[o]
            eps = 0.1 * radius[i] if np.isnan(obs.smoothing[o]) else obs.smoothing[o]
            f, df = penalty(delta, k, eps)
            w = weight[i]
            idx[c], ob_of[c], gap[c] = i, o, -delta
            for r in range(3):
                n_out[c, r] = n[r]
                F[c, r] = w * f * n[r]
                for s in range(3):
                    dF[c, r, s] = w * (-df * n[r] * n[s] + f * H[r, s])
            c += 1
    return c


@_jit
def step_contacts(radius, modulus, weight, allowed, obs, obs0, obst, moving, ovel0, p0, p1, pt, h, theta, v0,
                  use_v0, R0, R1, w0, idx, ob_of, n_out, gap, F, dF, dV, dFf, dVf, M, slip, spin, dW):
    """A time step from positions p0 to p1 (P, 3), forces at the theta
    point pt: every ``allowed`` (P, O) pair pressed in at either end,
    obstacle-major (sizes P O; returns the count). The obstacles: ``obs``
    at the step's end, ``obs0`` at its start and ``obst`` at its theta
    point (the same for those that do not move). The normal force is the
    mean force of the penetrations at the ends (against obs0 at the start
    for a ``moving`` obstacle), along the normal at pt, times the
    Hunt-Crossley factor ``max(1 + alpha (delta1 - delta0)/h, 0)``.

    Friction acts at the contact surface, the point ``l = -r n`` from the
    backbone point, against that point's slip at the end of the step (as
    implicit Euler would): ``(I - n n^T) v_p + (omega_rel x l)``, v_p the
    backbone point's velocity (v0: the points' start velocities,
    ``use_v0``) relative to a moving obstacle's material point (the one at
    p1 at the end was at ``x0 = a0 + R0 R1^T (p1 - a1)`` at the start:
    translation and rotation; its velocity at the end of the step, from
    the mean ``(p1 - x0) / h`` and, for the bodies' shapes, its velocity at
    the start, ``ovel0`` (O, 6): [velocity at a0; angular velocity]; NaN:
    the mean for a prescribed motion), omega_rel the angular velocity of
    the point's frame (rotations R0, R1 (P, 3, 3) at the step's ends,
    angular velocity w0 (P, 3) at its start) relative to the obstacle's.
    So a cross-section rolling without slip feels no friction (a ball on
    an incline rolls at 5/7 g sin(alpha)), and friction only ever
    dissipates. On the backbone point it is the force Ft and the moment
    ``l x Ft``. An obstacle with torsional friction (``obs.torsion``)
    resists the spin about the normal, omega_rel . n: ``M += m n``
    (:func:`spin_friction`), spin its rate [rad/s], dW = dm/dspin / theta.

    Outputs: F, M the force and moment on the backbone point; dF (the
    normal force's, through p1: 1/theta) and dV (d/dv1) act through the
    backbone point's Jacobian J_p; the friction's dFf (through p1, its
    normal force's growth) acts as ``J_s^T dFf J_p`` and its dVf as
    ``J_s^T dVf J_s``, with J_s = J_p + r [n x] J_omega the surface
    point's Jacobian (:func:`soft_twin_core.engine.contact_step._surface_jacobian`);
    slip: the surface point's tangential velocity."""
    n = np.empty(3)
    H = np.empty((3, 3))
    n0 = np.empty(3)
    H0 = np.empty((3, 3))
    vel = np.empty(3)
    sl = np.empty(3)
    Ft = np.empty(3)
    dFt = np.empty((3, 3))
    wm = np.empty(3)
    wo = np.empty(3)
    c = 0
    for o in range(obs.kind.shape[0]):
        bound1 = bounding_sphere(obs, o)
        bound0 = bounding_sphere(obs0, o) if moving[o] else bound1
        for i in range(p0.shape[0]):
            if not allowed[i, o]:
                continue
            r_i = radius[i]
            if far_from(bound1, p1, i, r_i) and far_from(bound0, p0, i, r_i):
                continue
            src = obs0 if moving[o] else obs
            d0 = distance(src, o, p0[i], n0, H0)
            d1 = distance(obs, o, p1[i], n0, H0)
            if not (r_i - d0 > 0.0 or r_i - d1 > 0.0):
                continue
            dt_ = distance(obst, o, pt[i], n, H)
            k = modulus[i] if np.isnan(obs.stiffness[o]) else obs.stiffness[o]
            eps = 0.1 * r_i if np.isnan(obs.smoothing[o]) else obs.smoothing[o]
            fbar, dfbar = mean_force(r_i - d0, r_i - d1, k, eps)
            fac = max(1.0 + obs.damping[o] * ((d0 - d1) / h), 0.0)
            w = weight[i]
            fn = w * fac * fbar
            dv = obs.damping[o] if fac > 0.0 else 0.0
            idx[c], ob_of[c], gap[c] = i, o, dt_ - r_i
            vn = 0.0
            for r in range(3):
                vel[r] = (p1[i, r] - p0[i, r]) / h
                if use_v0:
                    vel[r] = (vel[r] - (1.0 - theta) * v0[i, r]) / theta
            if moving[o]:
                for r in range(3):
                    # the obstacle's material point at p1: x0 = a0 + R0 R1^T (p1 - a1) at the start
                    x0 = obs0.a[o, r]
                    for a_ in range(3):
                        loc = 0.0
                        for b_ in range(3):
                            loc += obs.rotation[o, b_, a_] * (p1[i, b_] - obs.a[o, b_])
                        x0 += obs0.rotation[o, r, a_] * loc
                    sl[r] = x0
                for r in range(3):
                    um = (p1[i, r] - sl[r]) / h
                    if use_v0 and not np.isnan(ovel0[o, 0]):
                        r1, r2 = (r + 1) % 3, (r + 2) % 3
                        u0 = ovel0[o, r] + ovel0[o, 3 + r1] * (sl[r2] - obs0.a[o, r2]) - \
                            ovel0[o, 3 + r2] * (sl[r1] - obs0.a[o, r1])
                        um = (um - (1.0 - theta) * u0) / theta
                    vel[r] -= um
            for r in range(3):
                vn += vel[r] * n[r]
            for r in range(3):
                sl[r] = vel[r] - vn * n[r]
                n_out[c, r] = n[r]
                F[c, r] = fn * n[r]
                M[c, r] = 0.0
            spin[c], dW[c] = 0.0, 0.0
            rolls = obs.friction[o] > 0.0 and r_i > 0.0
            if obs.torsion[o] > 0.0 or rolls:
                # the frame's angular velocity at the step's end, relative to the obstacle's
                rotation_rate(R0[i], R1[i], h, wm)
                wo[:] = 0.0
                if moving[o]:
                    rotation_rate(obs0.rotation[o], obs.rotation[o], h, wo)
                for r in range(3):
                    if use_v0:
                        wm[r] = (wm[r] - (1.0 - theta) * w0[i, r]) / theta
                        if not np.isnan(ovel0[o, 0]):
                            wo[r] = (wo[r] - (1.0 - theta) * ovel0[o, 3 + r]) / theta
                    wm[r] -= wo[r]
            if obs.torsion[o] > 0.0:
                om = wm[0] * n[0] + wm[1] * n[1] + wm[2] * n[2]
                mt, dm = spin_friction(fn, om, obs.torsion[o], obs.stiction[o])
                spin[c], dW[c] = om, dm / theta
                for r in range(3):
                    M[c, r] = mt * n[r]
            if rolls:               # the surface point's slip: + omega x (-r n) = r n x omega
                sl[0] += r_i * (n[1] * wm[2] - n[2] * wm[1])
                sl[1] += r_i * (n[2] * wm[0] - n[0] * wm[2])
                sl[2] += r_i * (n[0] * wm[1] - n[1] * wm[0])
            for r in range(3):
                slip[c, r] = sl[r]
                for s in range(3):
                    dF[c, r, s] = w * fac * (-(dfbar / theta) * n[r] * n[s] + fbar * H[r, s])
                    dV[c, r, s] = -w * fbar * dv * n[r] * n[s]
                    dFf[c, r, s] = 0.0
                    dVf[c, r, s] = 0.0
            if obs.friction[o] > 0.0:
                friction(fn, sl, obs.friction[o], obs.stiction[o], Ft, dFt)
                # slip = (I - n n^T) v1 + ...: Newton's matrix has theta Dt; friction grows with the normal
                # force: dFt/dp = -mu (slip/s) dfn/dp^T, dfn/dp = -w fac fbar'/theta n, and with its
                # Hunt-Crossley factor: dfn/dv = -w fbar alpha n (as dV)
                g = w * fac * dfbar / theta
                gv = w * fbar * dv
                for r in range(3):
                    F[c, r] += Ft[r]
                    unit = Ft[r] / max(fn, 1e-300)
                    for s in range(3):
                        acc = 0.0
                        for q in range(3):
                            acc += dFt[r, q] * ((1.0 if q == s else 0.0) - n[q] * n[s])
                        dVf[c, r, s] = acc / theta - unit * gv * n[s]
                        dFf[c, r, s] = -unit * g * n[s]
                if rolls:           # its moment about the backbone point: (-r n) x Ft
                    M[c, 0] -= r_i * (n[1] * Ft[2] - n[2] * Ft[1])
                    M[c, 1] -= r_i * (n[2] * Ft[0] - n[0] * Ft[2])
                    M[c, 2] -= r_i * (n[0] * Ft[1] - n[1] * Ft[0])
            c += 1
    return c


# --- element-wise over arrays (engine.contact's array functions) ------------------

@_jit
def penalty_arrays(delta, k, eps, f, df, phi):
    for i in range(delta.shape[0]):
        f[i], df[i] = penalty(delta[i], k[i], eps[i])
        phi[i] = penalty_potential(delta[i], k[i], eps[i])


@_jit
def mean_force_arrays(d0, d1, k, eps, fbar, dfbar):
    for i in range(d0.shape[0]):
        fbar[i], dfbar[i] = mean_force(d0[i], d1[i], k[i], eps[i])


@_jit
def distance_arrays(obs, o, p, d, n, H):
    for i in range(p.shape[0]):
        d[i] = distance(obs, o, p[i], n[i], H[i])


@_jit
def friction_arrays(fn, vt, mu, v_s, F, dF):
    for i in range(fn.shape[0]):
        friction(fn[i], vt[i], mu, v_s, F[i], dF[i])
