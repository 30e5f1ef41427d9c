"""Runs from the twin node's messages: an MCAP recording of the node (its
``record_file``, ROS 2 bag format) or messages received live, turned into
the time histories of :func:`scenario.run_dynamics` so that the same
figures and animations are drawn from them (``soft-twin-sim render
FILE.mcap``), from the topics every twin node publishes (``backbone``,
``tip_pose``, ``strains``); :mod:`mechanism_recording` reads the joint,
member and frame topics as well, and writes a run in the node's topics.

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


def run_from_messages(backbones, tip_poses, strains, mech):
    """The run (fields of :func:`mechanism_scenario.run_mechanism_dynamics`)
    of the states whose backbone, tip pose and strains messages (same header
    stamp) are all given, the topics every twin node publishes: ``time`` [s]
    from the first such stamp, ``tip_position`` (world, the node's
    base_frame), ``strains``/``strain_rates`` (n_sections, 6) with
    ``section_names``, and a member sample per state: the backbone as the
    robot's main member (:func:`outputs.main_member`), the tip pose as its
    tip frame (``frame_poses``). A robot with other members or frames needs
    their topics: :func:`mechanism_recording.articulated_run_from_messages`."""
    from .mechanism import tip_frame
    from .outputs import main_member
    tip = tip_frame(mech)
    main = main_member(mech, tip)
    if len(mech.members) != 1 or list(mech.frames) != [tip]:
        raise ValueError(f"robot {mech.name!r} has members {[m.name for m in mech.members]} and frames "
                         f"{list(mech.frames)}: the recording has no joint states, member backbones or /tf for "
                         f"them (is it this robot's?)")
    by = [{_stamp_ns(m.header): m for m in msgs} for msgs in (backbones, tip_poses, strains)]
    stamps = sorted(set(by[0]) & set(by[1]) & set(by[2]))
    if not stamps:
        raise ValueError("no state with a backbone, a tip pose and strains of the same stamp")
    tree = mech.tree
    t0 = stamps[0]
    out = {"time": [], "tip_position": [], "strains": [], "strain_rates": [], "members_time": [], "members": [],
           "frame_poses": [], "frame_positions": [], "frame_names": [tip], "member_names": [main.name],
           "joint_names": [], "section_names": [tree.joints[i].name for i in tree.soft_joints],
           "n_sections": len(tree.soft_joints)}
    for k in stamps:
        t = round(1e-9 * (k - t0), 9)        # whole nanoseconds: the nearest float to the decimal time
        b, tp, s = by[0][k], by[1][k], by[2][k]
        n = int(s.n_sections)
        if n != out["n_sections"]:
            raise ValueError(f"the recording has {n} sections, robot {mech.name!r} {out['n_sections']}: give "
                             f"the recorded robot's --sections")
        out["time"].append(t)
        out["tip_position"].append(_xyz(tp.pose.position))
        out["strains"].append(np.asarray(s.strains, dtype=float).reshape(n, 6).tolist())
        rates = np.asarray(s.strain_rates, dtype=float)
        out["strain_rates"].append(rates.reshape(n, 6).tolist() if rates.size == 6 * n else
                                   np.full((n, 6), np.nan).tolist())
        g = _pose_of(tp.pose)
        out["frame_poses"].append([g.tolist()])
        out["frame_positions"].append([g[:3, 3].tolist()])
        out["members_time"].append(t)
        out["members"].append({main.name: {"positions": [_xyz(p.position) for p in b.poses],
                                           "orientations": [_xyzw(p.orientation) for p in b.poses]}})
    return out


def _xyzw(q):
    return [float(q.x), float(q.y), float(q.z), float(q.w)]


def _pose_of(pose):
    """4x4 of a geometry_msgs/Pose (read by attribute)."""
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(_xyzw(pose.orientation)).as_matrix()
    T[:3, 3] = _xyz(pose.position)
    return T


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


def read_node_run(msgs, ns, mech):
    """The run of node ``ns`` (``/soft_twin``) in decoded messages {topic:
    [msg, ...]} from its backbone, tip pose and strains topics (see
    :func:`run_from_messages`)."""
    return run_from_messages(*(msgs[f"{ns}/{s}"] for s in STATE_TOPICS), mech)


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
