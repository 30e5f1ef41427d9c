"""Runs from the twin node's messages: an MCAP recording of the node (its
``record_file``, ROS 2 bag format) or messages received live, turned into
the time histories of :func:`scenario.run_dynamics` so that the same
figures and animations are drawn from them (``soft-twin-sim render
FILE.mcap``).

Decoding uses the ``mcap`` and ``mcap-ros2-support`` libraries (pure
Python; no ROS import). Messages are read by attribute (``header.stamp``,
``poses``, ``strains``), so rclpy messages received live go through
:func:`run_from_messages` alike.
"""

import numpy as np

STATE_TOPICS = ("backbone", "tip_pose", "strains")


def _stamp_ns(header):
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _xyz(p):
    return [float(p.x), float(p.y), float(p.z)]


def run_from_messages(backbones, tip_poses, strains, model=None):
    """Time histories (``run_dynamics`` fields) of the states whose
    backbone, tip pose and strains messages (same header stamp) are all
    given: ``time`` [s] from the first such stamp, ``tip_position`` (world,
    the node's base_frame), ``strains``/``strain_rates`` (n_sections, 6),
    the ``backbone`` (P, 3) of every state with ``backbone_time``, and
    ``backbone_s`` [m] (the model's sample abscissae when the model is given
    and fits, else the chord length along the polyline)."""
    from .kinematics import backbone_abscissae
    by = [{_stamp_ns(m.header): m for m in msgs} for msgs in (backbones, tip_poses, strains)]
    stamps = sorted(set(by[0]) & set(by[1]) & set(by[2]))
    if not stamps:
        raise ValueError("no state with a backbone, a tip pose and strains of the same stamp")
    t0 = stamps[0]
    out = {"time": [], "tip_position": [], "strains": [], "strain_rates": [], "backbone_time": [],
           "backbone_s": [], "backbone": []}
    for k in stamps:
        t = 1e-9 * (k - t0)
        b, tp, s = by[0][k], by[1][k], by[2][k]
        n = int(s.n_sections)
        out["time"].append(t)
        out["tip_position"].append(_xyz(tp.pose.position))
        out["strains"].append(np.asarray(s.strains, dtype=float).reshape(n, 6).tolist())
        out["strain_rates"].append(np.asarray(s.strain_rates, dtype=float).reshape(n, 6).tolist())
        P = np.array([_xyz(p.position) for p in b.poses])
        if model is not None and (len(P) - 1) % model.n_sections == 0 and len(P) > 1:
            sb = backbone_abscissae(model, (len(P) - 1) // model.n_sections)
        else:
            sb = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
        out["backbone_time"].append(t)
        out["backbone_s"].append(sb.tolist())
        out["backbone"].append(P.tolist())
    out["n_sections"] = n
    return out


def read_messages(path, topics=None):
    """{topic: [decoded message, ...]} of an MCAP file in the ROS 2 format
    (log-time order); ``topics``: keep only these."""
    from .mcap_salvage import read_decoded
    out = {}
    # a recording cut short (killed node, truncated file) is read up to its last
    # complete chunk, with a warning: soft_twin_core.mcap_salvage
    for channel, _, decoded in read_decoded(path, topics, ValueError):
        out.setdefault(channel.topic, []).append(decoded)
    return out


def node_namespaces(messages):
    """The node namespaces (``/soft_twin``) with all state topics in ``messages``."""
    ns = {t.rsplit("/", 1)[0] for t in messages if t.rsplit("/", 1)[-1] in STATE_TOPICS}
    return sorted(n for n in ns if all(f"{n}/{s}" in messages for s in STATE_TOPICS))


def read_node_run(path, node=None, model=None):
    """The run of one twin node recorded in an MCAP file (see
    :func:`run_from_messages`); ``node``: its name when the file holds
    several."""
    msgs = read_messages(path)
    found = node_namespaces(msgs)
    if node is not None:
        ns = "/" + node.strip("/")
        if ns not in found:
            raise ValueError(f"{path}: no recorded state of node {ns!r}; found {found}")
    elif len(found) == 1:
        ns = found[0]
    else:
        raise ValueError(f"{path}: " + (f"several twin nodes recorded {found}: choose one with --node"
                                        if found else "no twin state topics (backbone, tip_pose, strains)"))
    return run_from_messages(*(msgs[f"{ns}/{s}"] for s in STATE_TOPICS), model=model)


# ----------------------------------------------------------------------------
# Writing a simulated run in the node's format
# ----------------------------------------------------------------------------

_SEP = "=" * 80
_DEFS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/PoseArray": "std_msgs/Header header\nPose[] poses\n",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\nPose pose\n",
    "soft_twin/Strains": ("std_msgs/Header header\nuint32 n_sections\nfloat64[] strains\nfloat64[] strain_rates\n"
                          "std_msgs/Header last_command\n"),
}
_DEPS = {
    "geometry_msgs/PoseArray": ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose",
                                "geometry_msgs/Point", "geometry_msgs/Quaternion"),
    "geometry_msgs/PoseStamped": ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Pose",
                                  "geometry_msgs/Point", "geometry_msgs/Quaternion"),
    "soft_twin/Strains": ("std_msgs/Header", "builtin_interfaces/Time"),
}


def _definition(name):
    """ros2msg schema text of one of the node's state messages (the field
    lines of the .msg files, dependencies after 80 '=' and ``MSG:``)."""
    return _DEFS[name] + "".join(f"{_SEP}\nMSG: {d}\n{_DEFS[d]}" for d in _DEPS[name])


def _pose_dict(T):
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    p = T[:3, 3]
    return {"position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
            "orientation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}}


def write_run_mcap(out, model, path, node="soft_twin_sim", frame="base_link", points_per_section=None):
    """Write the backbone samples of a dynamics run (:func:`scenario.run_dynamics`
    with ``backbone_every``) as the twin node would publish them: ``/<node>/backbone``
    (PoseArray: poses of the cross-sections from the strains, by the model's
    kinematics), ``/<node>/tip_pose`` and ``/<node>/strains``, stamped with the
    run's time (t = 0 at stamp 0). Returns the number of states written.
    ``soft-twin-sim render FILE.mcap`` draws it like a recording of the node."""
    from mcap_ros2.writer import Writer
    from .kinematics import backbone as backbone_poses
    if not out.get("backbone_time"):
        raise ValueError("the run has no backbone samples: run dynamics with --backbone-every K (K >= 1)")
    rows = {t: i for i, t in enumerate(out["time"])}
    n_pts = len(out["backbone"][0])
    pps = points_per_section or max(1, (n_pts - 1) // model.n_sections)
    ns = "/" + node.strip("/")
    with open(path, "wb") as fh:
        w = Writer(fh)
        schemas = {name: w.register_msgdef(name.replace("/", "/msg/"), _definition(name))
                   for name in ("geometry_msgs/PoseArray", "geometry_msgs/PoseStamped", "soft_twin/Strains")}
        for k, t in enumerate(out["backbone_time"]):
            i = rows[t]
            S = np.asarray(out["strains"][i], dtype=float)
            q = model.q_from_strains(S)
            _, T = backbone_poses(model, q, pps)
            stamp_ns = int(round(t * 1e9))
            header = {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000},
                      "frame_id": frame}
            w.write_message(f"{ns}/backbone", schemas["geometry_msgs/PoseArray"],
                            {"header": header, "poses": [_pose_dict(x) for x in T]}, stamp_ns, stamp_ns, k)
            w.write_message(f"{ns}/tip_pose", schemas["geometry_msgs/PoseStamped"],
                            {"header": header, "pose": _pose_dict(T[-1])}, stamp_ns, stamp_ns, k)
            w.write_message(f"{ns}/strains", schemas["soft_twin/Strains"],
                            {"header": header, "n_sections": model.n_sections, "strains": S.ravel().tolist(),
                             "strain_rates": np.asarray(out["strain_rates"][i], float).ravel().tolist(),
                             "last_command": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""}},
                            stamp_ns, stamp_ns, k)
        w.finish()
    return len(out["backbone_time"])
