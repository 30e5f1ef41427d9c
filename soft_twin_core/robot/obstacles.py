"""Obstacles and contact points of a robot file (the ``obstacles`` list and
the ``contact`` settings, in either schema), checked at the door::

    obstacles:                       # world frame [m]
      - {name: table, type: plane, point: [0, 0, -0.1], normal: [0, 0, 1]}
      - {name: ball, type: sphere, center: [0.3, 0, 0], radius: 0.05}
      - {name: post, type: capsule, from: [0.2, -0.1, 0], to: [0.2, 0.1, 0], radius: 0.01}
      - {name: block, type: box, center: [0.3, 0, -0.1], size: [0.1, 0.2, 0.05], rpy: [0, 0, 0.3]}
      - {name: wedge, type: mesh, vertices: [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]],
         faces: [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]}   # closed, convex or not (faces turned outward)
      - {name: vessel, type: tube, path: [[0, 0, 0], [0.1, 0, 0], [0.17, 0.03, 0]], radius: 0.004}
        # the free space is inside: within radius of the centre line (a polyline, open at its ends)
      # each may add: stiffness [N/m^2] (default: the member's Young's modulus),
      # smoothing [m] (default: a tenth of the member's radius), damping [s/m] (Hunt-Crossley
      # alpha, default 0), friction (Coulomb mu, default 0), stiction_velocity [m/s]
      # (the regularisation: a load held at half the friction limit creeps at 0.58 of it, default 1e-4),
      # torsional_friction [m] (the spin friction of a contact patch: a moment about the normal of
      # at most torsional_friction x the normal force; default 0)
    contact:
      spacing: 0.01                  # [m] between contact points along every member
                                     # (default: the smaller of 10 mm and a twentieth of the member)

The contact law: :mod:`soft_twin_core.engine.contact`.
"""

from dataclasses import replace

import numpy as np

from soft_twin_core import lie
from soft_twin_core.engine.contact import OBSTACLE_KINDS, ContactPoints, Obstacle, sample_path
from soft_twin_core.robot.model import ModelError, _check_keys, _num, _vec, pose_from_dict

_FIELDS = {"plane": ("point", "normal"), "sphere": ("center", "radius"), "capsule": ("from", "to", "radius"),
           "box": ("center", "size", "rpy", "quaternion"), "tube": ("path", "radius"),
           "mesh": ("vertices", "faces", "file", "scale", "position", "rpy", "quaternion")}
_COMMON = {"name", "type", "stiffness", "smoothing", "damping", "friction", "stiction_velocity",
           "torsional_friction"}


def obstacle_from_dict(d, where, base_dir=None):
    """An :class:`Obstacle` of one ``obstacles`` entry; ModelError naming the
    bad field (unknown type or key, non-finite or negative sizes, a zero
    normal, a capsule of zero length, a mesh file that cannot be read).
    ``base_dir``: the folder a mesh's ``file`` is relative to (the robot or
    scenario file's; None: the working directory)."""
    _check_keys(d, _COMMON | {"point", "normal", "center", "radius", "from", "to", "size", "rpy", "quaternion",
                              "vertices", "faces", "path", "file", "scale", "position"}, where)
    kind = d.get("type")
    if kind not in OBSTACLE_KINDS:
        raise ModelError(f"{where}.type: expected one of {sorted(OBSTACLE_KINDS)}, got {kind!r}")
    _check_keys(d, _COMMON | set(_FIELDS[kind]), where)
    name = d.get("name", where)
    if not isinstance(name, str) or not name:
        raise ModelError(f"{where}.name: expected a non-empty string, got {name!r}")
    common = contact_law(d, where)
    if kind == "plane":
        normal = _vec(d, "normal", 3, where)
        nn = np.linalg.norm(normal)
        if not nn > 0:
            raise ModelError(f"{where}.normal: must not be zero")
        return Obstacle(name, kind, _vec(d, "point", 3, where), normal / nn, **common)
    if kind == "box":
        size = _vec(d, "size", 3, where)
        if not np.all(size > 0):
            raise ModelError(f"{where}.size: the box's edge lengths must be > 0 m, got {size.tolist()}")
        T = pose_from_dict({k: d[k] for k in ("rpy", "quaternion") if k in d} or None, where)
        return Obstacle(name, kind, _vec(d, "center", 3, where), rotation=T[:3, :3].copy(), half_size=0.5 * size,
                        **common)
    if kind == "mesh":
        T = pose_from_dict({k: d[k] for k in ("position", "rpy", "quaternion") if k in d} or None, where)
        centre, tri = closed_mesh(*mesh_source(d, where, base_dir), where)
        return Obstacle(name, kind, T[:3, :3] @ centre + T[:3, 3], rotation=T[:3, :3].copy(), triangles=tri,
                        **common)
    radius = _num(d, "radius", where, positive=True)
    if kind == "tube":
        path = tube_path(d.get("path"), where)
        return Obstacle(name, kind, path[0].copy(), radius=radius, rotation=np.eye(3),
                        path=np.ascontiguousarray(path - path[0]), **common)
    if kind == "sphere":
        return Obstacle(name, kind, _vec(d, "center", 3, where), None, radius, **common)
    a, b = _vec(d, "from", 3, where), _vec(d, "to", 3, where)
    if not np.linalg.norm(b - a) > 0:
        raise ModelError(f"{where}: 'from' and 'to' must differ (a capsule of zero length is a sphere)")
    return Obstacle(name, kind, a, b, radius, **common)


MESH_FILES = (".stl", ".obj")


def mesh_source(d, where, base_dir=None):
    """(vertices (V, 3) [m], faces (F, 3)) of a mesh entry: inline
    ``vertices`` and ``faces``, or a ``file`` (STL, binary or ASCII, or
    Wavefront OBJ; relative to ``base_dir``) times ``scale`` (default 1:
    the file in metres; 0.001 for millimetres). ModelError naming the
    field."""
    if "file" not in d:
        if "scale" in d:
            raise ModelError(f"{where}.scale: scales a mesh 'file'; the inline vertices are in metres")
        return d.get("vertices"), d.get("faces")
    if "vertices" in d or "faces" in d:
        raise ModelError(f"{where}: a mesh is either 'file' or 'vertices' and 'faces', not both")
    scale = _num(d, "scale", where, positive=True) if "scale" in d else 1.0
    V, F = read_mesh_file(d["file"], f"{where}.file", base_dir)
    return V * scale, F


def read_mesh_file(name, where, base_dir=None):
    """(vertices (V, 3), faces (F, 3) int) of a mesh file: STL (binary or
    ASCII; its corners welded where they coincide exactly) or Wavefront OBJ
    (``v`` and ``f`` lines; polygons split into fans; 1-based or negative
    indices; texture and normal indices ignored). ModelError naming
    ``where`` and the file for a missing or unreadable file, an unknown
    extension, a truncated STL or an OBJ face index out of range."""
    import os
    if not isinstance(name, str) or not name:
        raise ModelError(f"{where}: expected a mesh file's path (.stl or .obj), got {name!r}")
    path = os.path.join(base_dir or "", os.path.expanduser(name))
    ext = os.path.splitext(path)[1].lower()
    if ext not in MESH_FILES:
        raise ModelError(f"{where}: {name!r}: expected an .stl or .obj file")
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise ModelError(f"{where}: cannot read {path!r}: {e.strerror or e}") from None
    return _read_stl(data, where, path) if ext == ".stl" else _read_obj(data, where, path)


def _read_stl(data, where, path):
    """An STL's triangles, binary (80-byte header, a uint32 count, 50 bytes
    a triangle) or ASCII (``vertex x y z`` lines), corners welded."""
    n = int(np.frombuffer(data[80:84], "<u4")[0]) if len(data) >= 84 else -1
    if n >= 0 and len(data) == 84 + 50 * n:
        rec = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
        corners = np.frombuffer(data, rec, count=n, offset=84)["corners"].astype(float)
    elif data.lstrip()[:5].lower() == b"solid":
        words = data.decode("ascii", "replace").split()
        at = [i for i, w in enumerate(words) if w == "vertex"]
        try:
            corners = np.array([[float(w) for w in words[i + 1:i + 4]] for i in at]).reshape(-1, 3, 3)
        except ValueError:
            raise ModelError(f"{where}: {path!r}: an ASCII STL 'vertex' line without three numbers") from None
        if len(at) % 3:
            raise ModelError(f"{where}: {path!r}: {len(at)} vertices, not whole triangles")
    else:
        raise ModelError(f"{where}: {path!r}: neither a binary STL ({len(data)} bytes for "
                         f"{max(n, 0)} triangles) nor an ASCII one (starting 'solid')")
    V, F = np.unique(corners.reshape(-1, 3), axis=0, return_inverse=True)
    return V, F.reshape(-1, 3)


def _read_obj(data, where, path):
    """An OBJ's vertices and its faces (polygons as fans)."""
    V, F = [], []
    for k, line in enumerate(data.decode("utf-8", "replace").splitlines(), 1):
        w = line.split()
        if not w or w[0] not in ("v", "f"):
            continue
        try:
            if w[0] == "v":
                V.append([float(x) for x in w[1:4]])
                continue
            idx = [int(x.split("/")[0]) for x in w[1:]]
        except ValueError:
            raise ModelError(f"{where}: {path!r} line {k}: expected numbers, got {line.strip()!r}") from None
        idx = [i - 1 if i > 0 else len(V) + i for i in idx]
        if len(idx) < 3 or not all(0 <= i < len(V) for i in idx):
            raise ModelError(f"{where}: {path!r} line {k}: a face needs 3 or more indices of the {len(V)} "
                             f"vertices before it, got {line.strip()!r}")
        F += [[idx[0], idx[j], idx[j + 1]] for j in range(1, len(idx) - 1)]
    return np.array(V, dtype=float).reshape(-1, 3), np.array(F, dtype=np.int64).reshape(-1, 3)


def closed_mesh(vertices, faces, where):
    """(centre, triangles (T, 3, 3) about it, outward) of a closed triangle
    mesh, convex or not (its faces in either winding: turned to one, then
    outward); ModelError naming the field: vertices not finite triples (at
    least 4), faces not index triples into them (at least 4), a face of zero
    area, an edge not shared by exactly two faces (not closed), faces whose
    windings cannot agree (not orientable: a face met from both sides)."""
    try:
        V = np.array(vertices, dtype=float)
    except (TypeError, ValueError):
        V = np.zeros((0,))
    if V.ndim != 2 or V.shape[1:] != (3,) or len(V) < 4 or not np.all(np.isfinite(V)):
        raise ModelError(f"{where}.vertices: expected at least 4 finite [x, y, z] points [m], got "
                         f"{str(vertices)[:200]}")
    try:
        F = np.array(faces)
        ok = F.ndim == 2 and F.shape[1:] == (3,) and len(F) >= 4 and np.issubdtype(F.dtype, np.integer)
    except (TypeError, ValueError):
        ok = False
    if not ok or F.min() < 0 or F.max() >= len(V):
        raise ModelError(f"{where}.faces: expected at least 4 triples of vertex indices in 0..{len(V) - 1}, got "
                         f"{str(faces)[:200]}")
    size = float(np.ptp(V, axis=0).max())
    centre = V.mean(axis=0)
    tri = V[F] - centre
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if np.any(area <= 1e-12 * size * size):
        raise ModelError(f"{where}.faces[{int(np.argmin(area))}]: a face of zero area")
    by_edge = _faces_by_edge(F)
    bad = next(((e, t) for e, t in by_edge.items() if len(t) != 2), None)
    if bad is not None:
        raise ModelError(f"{where}.faces: the mesh is not closed: edge {list(map(int, bad[0]))} belongs to "
                         f"{len(bad[1])} face(s), not 2")
    F, part, clash = _one_winding(F, by_edge)
    if clash is not None:
        raise ModelError(f"{where}.faces[{clash}]: the faces' windings cannot agree (a surface that is not "
                         "orientable, or one that meets itself)")
    tri = V[F] - centre
    for k in range(part.max() + 1):                 # each closed piece outward: its volume positive
        mine = part == k
        t = tri[mine]
        if np.einsum("ij,ij->", t[:, 0], np.cross(t[:, 1], t[:, 2])) < 0:
            tri[mine] = t[:, ::-1]
    return centre, np.ascontiguousarray(tri)


def _faces_by_edge(F):
    """{(i, j), i < j: the faces having that edge}."""
    out = {}
    for t, f in enumerate(F):
        for k in range(3):
            a, b = int(f[k]), int(f[(k + 1) % 3])
            out.setdefault((min(a, b), max(a, b)), []).append(t)
    return out


def _one_winding(F, by_edge):
    """(faces turned so that each edge runs once each way, each face's
    connected piece, the first face that cannot agree with its neighbours
    or None): a walk over neighbours from a face of each piece."""
    F = np.array(F, dtype=np.int64)
    part = np.full(len(F), -1)
    for seed in range(len(F)):
        if part[seed] >= 0:
            continue
        part[seed] = k = part.max() + 1
        stack = [seed]
        while stack:
            t = stack.pop()
            for i in range(3):
                a, b = F[t, i], F[t, (i + 1) % 3]
                for u in by_edge[(min(a, b), max(a, b))]:
                    if u == t:
                        continue
                    along = any(F[u, j] == a and F[u, (j + 1) % 3] == b for j in range(3))   # as t runs it
                    if part[u] >= 0:
                        if along:
                            return F, part, u
                        continue
                    if along:
                        F[u] = F[u, ::-1]
                    part[u] = k
                    stack.append(u)
    return F, part, None


def tube_path(path, where):
    """(N, 3) [m] a tube's centre line; ModelError naming the field: not at
    least 2 finite [x, y, z] points, or two consecutive ones the same."""
    try:
        P = np.array(path, dtype=float)
    except (TypeError, ValueError):
        P = np.zeros((0,))
    if P.ndim != 2 or P.shape[1:] != (3,) or len(P) < 2 or not np.all(np.isfinite(P)):
        raise ModelError(f"{where}.path: expected at least 2 finite [x, y, z] points [m], got {str(path)[:200]}")
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    if np.any(seg <= 1e-12 * max(float(np.ptp(P, axis=0).max()), 1e-300)):
        raise ModelError(f"{where}.path[{int(np.argmin(seg)) + 1}]: the same point as the one before it")
    return P


def contact_law(d, where):
    """The contact-law fields of an obstacle entry (Obstacle keywords), checked."""
    return dict(
        stiffness=_num(d, "stiffness", where, positive=True) if "stiffness" in d else None,
        smoothing=_num(d, "smoothing", where, positive=True) if "smoothing" in d else None,
        damping=_num(d, "damping", where, nonneg=True, default=0.0),
        stiction_velocity=_num(d, "stiction_velocity", where, positive=True, default=1e-4),
        friction=_num(d, "friction", where, nonneg=True, default=0.0),
        torsional_friction=_num(d, "torsional_friction", where, nonneg=True, default=0.0))


def obstacles_from_list(items, where="robot.obstacles", base_dir=None):
    """Obstacles of a robot file's or scenario's ``obstacles`` list (None:
    none); ``base_dir``: the folder mesh files are relative to."""
    if items is None:
        return ()
    if not isinstance(items, list):
        raise ModelError(f"{where}: expected a list of obstacles, got {items!r}")
    return check_unique_names(tuple(obstacle_from_dict(d, f"{where}[{i}]", base_dir) for i, d in enumerate(items)),
                              where)


def check_unique_names(obstacles, where):
    """``obstacles`` (a tuple), or ModelError naming the repeated names."""
    names = [o.name for o in obstacles]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ModelError(f"{where}: obstacle names must be unique, repeated: {dup}")
    return obstacles


def obstacle_at(name, kind, T, dimensions=(), law=None, where="obstacle", mesh=None):
    """An obstacle ``name`` of ``kind`` placed at the pose T (4x4, world <-
    obstacle), checked as a robot file's entry is (ModelError naming
    ``where``'s field): a plane through T's origin with T's z axis its
    normal; a sphere (dimensions [radius]) or box (dimensions [x, y, z] edge
    lengths) centred at it, the box along its axes; a capsule (dimensions
    [length, radius]) along its z axis, centred; a closed mesh (``mesh``:
    (vertices (V, 3) [m] in T's frame, faces (F, 3))) with T's frame as its
    own (a MOVE places that frame). ``law``: the contact-law keys
    (stiffness, smoothing, damping, friction, stiction_velocity,
    torsional_friction)."""
    T = np.asarray(T, dtype=float)
    if kind == "mesh":
        centre, tri = closed_mesh(*(mesh if mesh is not None else (None, None)), where)
        _check_keys(law or {}, _COMMON - {"name", "type"}, where)
        return Obstacle(name, "mesh", T[:3, 3].copy(), rotation=T[:3, :3].copy(),
                        triangles=np.ascontiguousarray(tri + centre), **contact_law(law or {}, where))
    c, R = T[:3, 3], T[:3, :3]
    dims = [float(x) for x in dimensions]
    need = {"plane": 0, "sphere": 1, "box": 3, "capsule": 2}.get(kind, 0)     # (a mesh: above)
    if len(dims) < need:
        raise ModelError(f"{where}.dimensions: a {kind} needs {need} dimensions, got {dims}")
    d = {"name": name, "type": kind, **(law or {})}
    if kind == "plane":
        d.update(point=c.tolist(), normal=R[:, 2].tolist())
    elif kind == "sphere":
        d.update(center=c.tolist(), radius=dims[0])
    elif kind == "box":
        d.update(center=c.tolist(), size=dims[:3])
    elif kind == "capsule":
        half = 0.5 * dims[0] * R[:, 2]
        d.update({"from": (c - half).tolist(), "to": (c + half).tolist(), "radius": dims[1]})
    ob = obstacle_from_dict(d, where)
    return replace(ob, rotation=R.copy()) if kind == "box" else ob


def obstacle_placed(ob, T):
    """The obstacle ``ob`` moved to the pose T (4x4) in the sense of
    :func:`obstacle_at` (its shape and contact law kept; a robot file's mesh:
    its vertices' mean and the world axes are its frame); ModelError for a
    pose that is not finite."""
    T = np.asarray(T, dtype=float)
    if not np.all(np.isfinite(T)):
        raise ModelError(f"obstacle {ob.name!r}: the pose must be finite, got {T[:3].tolist()}")
    if ob.kind == "plane":
        return replace(ob, a=T[:3, 3].copy(), b=T[:3, 2].copy())
    if ob.kind == "sphere":
        return replace(ob, a=T[:3, 3].copy())
    if ob.kind in ("box", "mesh", "tube"):
        return replace(ob, a=T[:3, 3].copy(), rotation=T[:3, :3].copy())
    half = 0.5 * np.linalg.norm(ob.b - ob.a) * T[:3, 2]
    return replace(ob, a=T[:3, 3] - half, b=T[:3, 3] + half)


# the contact stiffness [N/m^2 = Pa] of a link's round shape against the world when its
# ``collision`` gives none (that of a stiff rubber, as the soft members' modulus)
DEFAULT_SHAPE_STIFFNESS = 1.0e6
_SHAPES = {"sphere": ("radius",), "capsule": ("radius", "length"), "cylinder": ("radius", "length"),
           "box": ("size",), "mesh": ("vertices", "faces", "file", "scale")}


def link_shape(d, name, joint, where, base_dir=None):
    """A link's ``collision`` shape (None: none) as an :class:`Obstacle`
    carried by its joint ``joint`` (a, b, rotation in the link's frame),
    named after the link::

        collision: {shape: sphere | capsule | cylinder | box | mesh, radius, length, size,
                    vertices, faces | file, scale, position, rpy | quaternion,   # the shape's pose in the link
                    stiffness, smoothing, damping, friction, stiction_velocity, torsional_friction}

    A capsule or cylinder lies along the shape frame's z axis, centred
    (a cylinder is taken as a capsule: its ends rounded); a box has edge
    lengths ``size``; a mesh is closed (convex or not). The soft members touch
    it as they touch an obstacle; a sphere or capsule touches the world's
    obstacles too (:func:`contact_points`)."""
    if d is None:
        return None
    if not isinstance(d, dict):
        raise ModelError(f"{where}: expected a mapping {{shape, sizes, ...}}, got {d!r}")
    shape = d.get("shape")
    if shape not in _SHAPES:
        raise ModelError(f"{where}.shape: expected one of {sorted(_SHAPES)}, got {shape!r}")
    _check_keys(d, {"shape", "position", "rpy", "quaternion"} | set(_SHAPES[shape]) | (_COMMON - {"name", "type"}),
                where)
    T = pose_from_dict({k: d[k] for k in ("position", "rpy", "quaternion") if k in d} or None, where)
    law = {k: d[k] for k in _COMMON - {"name", "type"} if k in d}
    if shape == "mesh":
        ob = obstacle_at(name, "mesh", T, law=law, where=where, mesh=mesh_source(d, where, base_dir))
    else:
        dims = {"sphere": lambda: [_num(d, "radius", where, positive=True)],
                "box": lambda: list(_vec(d, "size", 3, where)),
                "capsule": lambda: [_num(d, "length", where, positive=True), _num(d, "radius", where, positive=True)]}
        kind = "capsule" if shape == "cylinder" else shape
        ob = obstacle_at(name, kind, T, dims[kind](), law, where)
    return replace(ob, body=int(joint))


def _shape_points(link, spacing):
    """(offset (k, 3), weight (k,), radius) of a link's round collision shape:
    a sphere's centre (standing for its diameter), or the midpoints of equal
    intervals of a capsule's axis at ``spacing`` (default: the smaller of
    10 mm and a twentieth of it); None for a box or mesh."""
    ob = link.collision
    if ob is None or ob.kind not in ("sphere", "capsule"):
        return None
    if ob.kind == "sphere":
        return ob.a[None, :].copy(), np.array([2.0 * ob.radius]), ob.radius
    L = float(np.linalg.norm(ob.b - ob.a))
    h = spacing if spacing is not None else min(0.01, L / 20)
    n = max(1, int(np.ceil(L / h - 1e-9)))
    t = (np.arange(n) + 0.5) / n
    return ob.a + t[:, None] * (ob.b - ob.a), np.full(n, L / n), ob.radius


_MEMBER_CONTACT = {"members", "self", "exclusion"} | (_COMMON - {"name", "type", "torsional_friction"})


def contact_spacing(d, where="robot.contact"):
    """The ``contact`` settings' spacing [m] (None: the default)."""
    if d is None:
        return None
    _check_keys(d, {"spacing", "between"}, where)
    return _num(d, "spacing", where, positive=True) if "spacing" in d else None


def member_contact(d, member_names, where="robot.contact.between"):
    """The ``contact.between`` settings of a robot file (None: none),
    checked against its members: ``(members, law, self, exclusion)``, the
    members (distinct; at least two, or one touching itself) whose surfaces
    touch one another, their contact law (:func:`contact_law`'s keys, the
    obstacles' defaults), whether each touches itself too (``self``,
    default false) beyond ``exclusion`` [m] of arc length from each capsule
    (None: four cross-section radii)::

        contact:
          between: {members: [finger_left, finger_right], friction: 0.5}
          between: {members: [arm], self: true}          # an arm coiling onto itself
    """
    if d is None:
        return None
    if not isinstance(d, dict):
        raise ModelError(f"{where}: expected a mapping {{members: [...], friction, ...}}, got {d!r}")
    _check_keys(d, _MEMBER_CONTACT, where)
    names = d.get("members")
    self_contact = d.get("self", False)
    if not isinstance(self_contact, bool):
        raise ModelError(f"{where}.self: expected true or false, got {self_contact!r}")
    least = 1 if self_contact else 2
    if not isinstance(names, list) or len(names) < least or len(set(map(str, names))) != len(names):
        raise ModelError(f"{where}.members: expected {'one' if self_contact else 'two'} or more distinct "
                         f"member names, got {names!r}")
    for n in names:
        if n not in member_names:
            raise ModelError(f"{where}.members: {n!r} is not a member of this robot; its members are "
                             f"{list(member_names)}")
    exclusion = _num(d, "exclusion", where, nonneg=True) if "exclusion" in d else None
    return (tuple(names), contact_law({k: v for k, v in d.items() if k not in ("members", "self", "exclusion")},
                                      where), self_contact, exclusion)


def member_capsules(tree, members, names, law, self_contact=False, exclusion=None):
    """The capsules along the members ``names`` (in that order) that the
    earlier ones' contact points touch: each pair of members touches once,
    the points of the one listed first against the capsules of the other
    (a second, mirrored contact would double the law's stiffness); with
    ``self_contact`` each member's own points touch its capsules too, those
    farther along its arc than ``exclusion`` [m] (None: four radii) from the
    capsule's ends (its neighbours, which bending brings close, do not). Each
    section's surface is two half-capsules of its cross-section radius (the
    larger extreme fibre distance, as its contact points'), each carried
    rigidly by the nearer section frame: the distal half by the section's
    end frame, the proximal half by the end frame of the member's section
    before it (by its own end frame for the first section), placed at the
    reference strain: off the bent section by about ``kappa (L/2)^2 / 2``.
    The members' own points never touch their capsules
    (:func:`soft_twin_core.solve.contact.contact_mask`)."""
    by_name = {m.name: m for m in members}
    out = []
    for k, name in enumerate(names):
        mem = by_name[name]
        touches = tuple(names[:k]) + ((name,) if self_contact else ())
        if not touches:
            continue
        path = tree.paths[mem.path]
        for i, (j, geo) in enumerate(zip(mem.joints, mem.geometry)):
            if geo is None:
                raise ModelError(f"robot.contact.between.members: member {name!r} has no cross_section (shape and "
                                 f"size): its surface has no radius")
            joint = tree.joints[j]
            sec = joint.section
            r = max(geo.cy, geo.cz)
            s0 = float(path.s_starts[list(path.joints).index(j)])
            gap = 4.0 * r if exclusion is None else exclusion
            half, full = lie.exp_se3(0.5 * sec.length * sec.f0), lie.exp_se3(sec.length * sec.f0)
            end = lie.se3_inv(full)                      # the section's start, seen from its end
            distal = (j, (end @ half)[:3, 3], np.zeros(3))
            if i > 0 and joint.parent == mem.joints[i - 1]:
                P = joint.placement                      # the section's start in the previous one's end frame
                proximal = (joint.parent, P[:3, 3].copy(), (P @ half)[:3, 3])
            else:
                proximal = (j, end[:3, 3].copy(), (end @ half)[:3, 3])
            for part, (body, a, b), (lo, hi) in zip("pd", (proximal, distal),
                                                    ((s0, s0 + sec.length / 2), (s0 + sec.length / 2, s0 + sec.length))):
                skips = (name, lo - gap, hi + gap) if self_contact else None
                out.append(Obstacle(f"{name}[{i}]{part}", "capsule", np.asarray(a, float), np.asarray(b, float),
                                    radius=float(r), body=int(body), touches=touches, skips=skips, **law))
    return tuple(out)


def contact_points(mech, spacing=None):
    """:class:`ContactPoints` of every soft member of ``mech``: points at
    ``spacing`` [m] (default: the smaller of 10 mm and a twentieth of the
    member), each with its section's cross-section radius (the larger
    extreme fibre distance) and Young's modulus (axial stiffness over
    area); then the points of the links' round collision shapes
    (:func:`_shape_points`, their stiffness: the shape's, default
    DEFAULT_SHAPE_STIFFNESS). ModelError for a member without a
    cross-section shape (a ``sectional`` stiffness gives no radius)."""
    tree = mech.tree
    J, X, W, R, E, M, S, OFF = [], [], [], [], [], [], [], []
    for mem in mech.members:
        path = tree.paths[mem.path]
        h = spacing if spacing is not None else min(0.01, path.length / 20)
        j, x, s, w = sample_path(path, h)
        for k, (jj, xx) in enumerate(zip(j, x)):
            geo = mem.geometry[list(mem.joints).index(int(jj))]
            if geo is None:
                raise ModelError(f"member {mem.name!r}: contact needs its cross_section (shape and size); "
                                 f"a sectional stiffness gives no radius")
            R.append(max(geo.cy, geo.cz))
            E.append(tree.joints[int(jj)].section.K[0, 0] / geo.A)
        J.append(j)
        X.append(x)
        W.append(w)
        S.append(s)
        OFF.append(np.zeros((len(j), 3)))
        M += [mem.name] * len(j)
    for link in mech.links:
        pts = _shape_points(link, spacing)
        if pts is None:
            continue
        off, w, r = pts
        k = len(w)
        J.append(np.full(k, link.joint, np.int64))
        X.append(np.full(k, -1.0))
        W.append(w)
        S.append(np.zeros(k))
        OFF.append(off)
        R += [r] * k
        E += [link.collision.stiffness or DEFAULT_SHAPE_STIFFNESS] * k
        M += [link.name] * k
    if not J:
        return ContactPoints(np.zeros(0, np.int64), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), (),
                             np.zeros(0))
    return ContactPoints(np.concatenate(J), np.concatenate(X), np.concatenate(W), np.array(R, float),
                         np.array(E, float), tuple(M), np.concatenate(S), np.ascontiguousarray(np.concatenate(OFF)))
