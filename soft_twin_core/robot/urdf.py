"""URDF for the rigid part of a soft articulated robot.

* :func:`bodies_from_urdf`: the links and joints of a rigid URDF as bodies
  of the tree robot schema (:mod:`mechanism`), so soft members can be
  mounted on them (a robot file's ``urdf:`` key; members name URDF links as
  parents). The URDF's root link is the base.
* :func:`to_urdf`: the rigid links and joints of a mechanism (those whose
  path to the base crosses no soft member) as URDF text, for RViz's
  robot_state_publisher and other ROS tools.

The two conventions agree: a URDF joint's ``origin`` is the joint frame in
the parent link's frame at zero position, its ``axis`` is in the joint
frame, the child link's frame is the joint frame; ``rpy`` is roll, pitch,
yaw about fixed axes (R = Rz(yaw) Ry(pitch) Rx(roll)); an inertial's
``origin`` places the centre of mass and the axes its inertia is given in.
Supported joint types: fixed, revolute, continuous, prismatic.
"""

import xml.etree.ElementTree as ET

import numpy as np

from soft_twin_core.engine.joint_kinds import FIXED, PRISMATIC, REVOLUTE
from soft_twin_core.robot.model import ModelError, pose_from_dict


def _floats(text, n, where):
    try:
        v = [float(x) for x in (text or "").split()]
    except ValueError:
        raise ModelError(f"{where}: expected {n} numbers, got {text!r}") from None
    if len(v) != n or not np.all(np.isfinite(v)):
        raise ModelError(f"{where}: expected {n} finite numbers, got {text!r}")
    return v


def _origin(el, where):
    o = el.find("origin") if el is not None else None
    if o is None:
        return [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
    return (_floats(o.get("xyz", "0 0 0"), 3, where + ".origin.xyz"),
            _floats(o.get("rpy", "0 0 0"), 3, where + ".origin.rpy"))


def _link_body(link, where):
    """mass, com, inertia (about the com, link axes) and visual of a URDF link."""
    out = {}
    inert = link.find("inertial")
    if inert is not None:
        xyz, rpy = _origin(inert, where + ".inertial")
        m = inert.find("mass")
        mass = float(m.get("value")) if m is not None else 0.0
        i = inert.find("inertia")
        I = np.zeros((3, 3))
        if i is not None:
            g = {k: float(i.get(k, 0.0)) for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")}
            I = np.array([[g["ixx"], g["ixy"], g["ixz"]], [g["ixy"], g["iyy"], g["iyz"]],
                          [g["ixz"], g["iyz"], g["izz"]]])
        R = pose_from_dict({"rpy": rpy}, where)[:3, :3]
        I = R @ I @ R.T
        out.update(mass=mass, com=xyz, inertia=[float(I[0, 0]), float(I[1, 1]), float(I[2, 2]),
                                                 float(I[0, 1]), float(I[0, 2]), float(I[1, 2])])
    vis = link.find("visual/geometry")
    if vis is not None and len(vis):
        g = vis[0]
        if g.tag == "box":
            out["visual"] = {"shape": "box", "size": _floats(g.get("size"), 3, where + ".visual.box.size")}
        elif g.tag == "cylinder":
            out["visual"] = {"shape": "cylinder", "radius": float(g.get("radius")), "length": float(g.get("length"))}
        elif g.tag == "sphere":
            out["visual"] = {"shape": "sphere", "radius": float(g.get("radius"))}
    return out


def bodies_from_urdf(text, source="urdf"):
    """Bodies (tree schema dicts, parents before children) of a rigid URDF;
    ModelError naming the element on anything unsupported."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise ModelError(f"{source}: invalid XML: {e}") from None
    if root.tag != "robot":
        raise ModelError(f"{source}: expected a <robot> element, got <{root.tag}>")
    links = {lk.get("name"): lk for lk in root.findall("link")}
    joints = root.findall("joint")
    child_of = {}
    for j in joints:
        c, p = j.find("child"), j.find("parent")
        if c is None or p is None:
            raise ModelError(f"{source}: joint {j.get('name')!r} needs <parent> and <child>")
        child_of[c.get("link")] = j
    roots = [n for n in links if n not in child_of]
    if len(roots) != 1:
        raise ModelError(f"{source}: expected one root link, got {roots}")
    order, frontier = [], [roots[0]]
    while frontier:                                   # parents before children
        parent = frontier.pop(0)
        for j in joints:
            if j.find("parent").get("link") == parent:
                order.append(j)
                frontier.append(j.find("child").get("link"))
    bodies = []
    for j in order:
        name, kind = j.get("name"), j.get("type")
        where = f"{source}: joint {name!r}"
        child, parent = j.find("child").get("link"), j.find("parent").get("link")
        if child not in links:
            raise ModelError(f"{where}: child link {child!r} is not defined")
        xyz, rpy = _origin(j, where)
        jd = {"name": name, "position": xyz, "rpy": rpy}
        if kind in ("revolute", "continuous", "prismatic"):
            jd["type"] = "prismatic" if kind == "prismatic" else "revolute"
            a = j.find("axis")
            jd["axis"] = _floats(a.get("xyz"), 3, where + ".axis") if a is not None else [1.0, 0.0, 0.0]
            lim = j.find("limit")
            if kind != "continuous" and lim is not None and lim.get("lower") is not None:
                jd["limits"] = [float(lim.get("lower")), float(lim.get("upper"))]
            dyn = j.find("dynamics")
            if dyn is not None and dyn.get("damping") is not None:
                jd["damping"] = float(dyn.get("damping"))
            jd["control"] = "position"
        elif kind == "fixed":
            jd["type"] = "fixed"
        else:
            raise ModelError(f"{where}: type {kind!r} is not supported (fixed, revolute, continuous, prismatic)")
        body = {"name": child, "type": "link", "parent": "base" if parent == roots[0] else parent, "joint": jd}
        body.update(_link_body(links[child], f"{source}: link {child!r}"))
        bodies.append(body)
    return bodies


def _r(x):
    """Shortest round-trip text of a number."""
    return repr(float(x))


def _fmt(v):
    return " ".join(_r(x) for x in v)


def _rpy(R):
    """Roll, pitch, yaw of R = Rz(y) Ry(p) Rx(r)."""
    p = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    if abs(np.cos(p)) > 1e-12:
        r = np.arctan2(R[2, 1], R[2, 2])
        y = np.arctan2(R[1, 0], R[0, 0])
    else:                                            # gimbal lock: put it all in yaw
        r, y = 0.0, np.arctan2(-R[0, 1], R[1, 1])
    return [r, p, y]


def to_urdf(mech, base_link="base_link"):
    """URDF text of the mechanism's rigid part (fixed base): every link and
    named frame whose chain to the base crosses no soft member, with its
    joint; mass, centre of mass, inertia and visual of the links."""
    tree = mech.tree
    if mech.base_motion != "fixed":
        raise ValueError("to_urdf: only robots with a fixed base")
    link_of = {lk.joint: lk for lk in mech.links}
    rigid = set()
    robot = ET.Element("robot", name=mech.name)
    ET.SubElement(robot, "link", name=base_link)
    for i, j in enumerate(tree.joints):
        if j.kind not in (FIXED, REVOLUTE, PRISMATIC) or not (j.parent == -1 or j.parent in rigid):
            continue
        rigid.add(i)
        lk = link_of.get(i)
        name = lk.name if lk is not None else j.name
        link = ET.SubElement(robot, "link", name=name)
        I6 = j.inertia
        mass = float(I6[0, 0])
        if mass > 0:
            c = np.array([I6[5, 1], I6[3, 2], I6[4, 0]]) / mass
            C = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
            Ic = I6[3:, 3:] + mass * C @ C
            inert = ET.SubElement(link, "inertial")
            ET.SubElement(inert, "origin", xyz=_fmt(c), rpy="0 0 0")
            ET.SubElement(inert, "mass", value=_r(mass))
            ET.SubElement(inert, "inertia", ixx=_r(Ic[0, 0]), iyy=_r(Ic[1, 1]), izz=_r(Ic[2, 2]),
                          ixy=_r(Ic[0, 1]), ixz=_r(Ic[0, 2]), iyz=_r(Ic[1, 2]))
        if lk is not None and lk.visual:
            v = lk.visual
            geo = ET.SubElement(ET.SubElement(link, "visual"), "geometry")
            if v["shape"] == "box":
                ET.SubElement(geo, "box", size=_fmt(v["size"]))
            elif v["shape"] == "cylinder":
                ET.SubElement(geo, "cylinder", radius=_r(v["radius"]), length=_r(v["length"]))
            else:
                ET.SubElement(geo, "sphere", radius=_r(v["radius"]))
        kind = {FIXED: "fixed", REVOLUTE: "revolute", PRISMATIC: "prismatic"}[j.kind]
        if kind == "revolute" and j.limits is None:
            kind = "continuous"
        jel = ET.SubElement(robot, "joint", name=j.name if lk is not None or j.kind != FIXED else f"{j.name}_joint",
                            type=kind)
        parent = base_link if j.parent == -1 else (link_of[j.parent].name if j.parent in link_of
                                                   else tree.joints[j.parent].name)
        ET.SubElement(jel, "parent", link=parent)
        ET.SubElement(jel, "child", link=name)
        ET.SubElement(jel, "origin", xyz=_fmt(j.placement[:3, 3]), rpy=_fmt(_rpy(j.placement[:3, :3])))
        if kind != "fixed":
            ET.SubElement(jel, "axis", xyz=_fmt(j.axis))
            vmax = mech.motion_limits.get(j.name, (1.0, 1.0))[0]
            lim = {"effort": "0", "velocity": _r(vmax)}
            if j.limits is not None:
                lim.update(lower=_r(j.limits[0]), upper=_r(j.limits[1]))
            ET.SubElement(jel, "limit", **lim)
            if j.damping:
                ET.SubElement(jel, "dynamics", damping=_r(j.damping))
    ET.indent(robot)
    return ET.tostring(robot, encoding="unicode") + "\n"
