"""MCAP recordings (ROS 2 bag format) of any robot: a simulated run
written as the twin node publishes it (:func:`write_articulated_mcap`), and
a recording (the node's ``record_file``, or that file) or messages received
live read back into the fields of a dynamics run
(:func:`mechanism_scenario.run_mechanism_dynamics`), so that the same
figures and animations are drawn from them (``soft-twin-sim render
FILE.mcap``; :func:`read_node_recording`).

Topics (``/<node>/...`` as the node names them)::

    backbone                geometry_msgs/PoseArray  the main member's (outputs.main_member)
    tip_pose                geometry_msgs/PoseStamped
    strains                 soft_twin/Strains        every soft section, tree order
    joint_states            sensor_msgs/JointState   positions, velocities, efforts of the rigid joints
    backbones/<member>      geometry_msgs/PoseArray  the member's backbone poses
    joint_wrenches/<joint>  geometry_msgs/WrenchStamped (the node: only while subscribed)
    /tf                     tf2_msgs/TFMessage       <node>/<frame> of every named frame

Every twin node publishes the first three (:func:`run_from_messages` reads
a run from them alone); with the others a state is one header stamp with
the joint states, every member's backbone and the frames on /tf
(:func:`articulated_run_from_messages`; the node sends /tf at
``tf_rate_hz``, so a node recording reads back at that rate).

Decoding uses the ``mcap`` and ``mcap-ros2-support`` libraries (pure
Python; no ROS import). Messages are read by attribute (``header.stamp``,
``poses``, ``strains``), so rclpy messages received live go through alike.
"""

import re

import numpy as np

from soft_twin_core.files.mcap_salvage import read_decoded, recorded_topics
from soft_twin_core.robot.mechanism import tip_frame, tip_frame as tip_frame_of
from soft_twin_core.solve.outputs import main_member


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
    their topics: :func:`recording.articulated_run_from_messages`."""
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
    out = {}
    # a recording cut short (killed node, truncated file) is read up to its last
    # complete chunk, with a warning: soft_twin_core.files.mcap_salvage
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


def _pose_dict(T):
    from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    p = T[:3, 3]
    return {"position": {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])},
            "orientation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}}


_DEFS.update({
    "sensor_msgs/JointState": "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
                              "float64[] effort\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "geometry_msgs/Wrench": "Vector3 force\nVector3 torque\n",
    "geometry_msgs/WrenchStamped": "std_msgs/Header header\nWrench wrench\n",
})
_DEPS.update({
    "sensor_msgs/JointState": ("std_msgs/Header", "builtin_interfaces/Time"),
    "tf2_msgs/TFMessage": ("geometry_msgs/TransformStamped", "std_msgs/Header", "builtin_interfaces/Time",
                           "geometry_msgs/Transform", "geometry_msgs/Vector3", "geometry_msgs/Quaternion"),
    "geometry_msgs/WrenchStamped": ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Wrench",
                                    "geometry_msgs/Vector3"),
})


def topic_name(name):
    """The node's topic token for a user-given name (``soft_twin.node._topic_name``)."""
    t = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return t if t and not t[0].isdigit() else f"_{t}"


def _definition(name):
    """ros2msg schema text of one of the node's messages (the field lines
    of the .msg files, dependencies after 80 '=' and ``MSG:``)."""
    return _DEFS[name] + "".join(f"{_SEP}\nMSG: {d}\n{_DEFS[d]}" for d in _DEPS[name])


def _pose_from_quat(p, q):
    from scipy.spatial.transform import Rotation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = p
    return T


def write_articulated_mcap(out, mech, path, node="soft_twin_sim", frame="base_link", tip_frame=None):
    """Write the member samples of an articulated run
    (:func:`mechanism_scenario.run_mechanism_dynamics` with ``backbone_every``)
    as the node publishes them (see the module), stamped with the run's time
    (t = 0 at stamp 0). Returns the number of states written."""
    from mcap_ros2.writer import Writer
    if not out.get("members_time") or "frame_poses" not in out:
        raise ValueError("the run has no member samples: run dynamics with --backbone-every K (K >= 1)")
    rows = {t: i for i, t in enumerate(out["time"])}
    ns = "/" + node.strip("/")
    prefix = node.strip("/") + "/"
    fnames = list(out["frame_names"])
    if tip_frame is None:
        tip_frame = tip_frame_of(mech)
    main = main_member(mech, tip_frame)
    tnames = list(out.get("transmitted_names", []))
    with open(path, "wb") as fh:
        w = Writer(fh)
        sch = {n: w.register_msgdef(n.replace("/", "/msg/"), _definition(n))
               for n in ("sensor_msgs/JointState", "geometry_msgs/PoseArray", "geometry_msgs/PoseStamped",
                         "soft_twin/Strains", "tf2_msgs/TFMessage", "geometry_msgs/WrenchStamped")}
        for k, (t, members, poses) in enumerate(zip(out["members_time"], out["members"], out["frame_poses"])):
            i = rows[t]
            ns_t = int(round(t * 1e9))
            stamp = {"sec": ns_t // 1_000_000_000, "nanosec": ns_t % 1_000_000_000}
            header = {"stamp": stamp, "frame_id": frame}

            def put(topic, schema, msg):
                w.write_message(topic, sch[schema], msg, ns_t, ns_t, k)

            put(f"{ns}/joint_states", "sensor_msgs/JointState",
                {"header": header, "name": list(out["joint_names"]),
                 "position": [float(x) for x in out["joint_positions"][i]],
                 "velocity": [float(x) for x in out["joint_velocities"][i]],
                 "effort": [float(x) for x in out["joint_efforts"][i]]})
            for name, m in members.items():
                P, Q = np.asarray(m["positions"], float), np.asarray(m["orientations"], float)
                msg = {"header": header, "poses": [_pose_dict(_pose_from_quat(p, q)) for p, q in zip(P, Q)]}
                put(f"{ns}/backbones/{topic_name(name)}", "geometry_msgs/PoseArray", msg)
                if main is not None and name == main.name:
                    put(f"{ns}/backbone", "geometry_msgs/PoseArray", msg)
            fp = dict(zip(fnames, poses))
            put(f"{ns}/tip_pose", "geometry_msgs/PoseStamped",
                {"header": header, "pose": _pose_dict(np.asarray(fp[tip_frame], float))})
            S = np.asarray(out["strains"][i], dtype=float)
            put(f"{ns}/strains", "soft_twin/Strains",
                {"header": header, "n_sections": len(S), "strains": S.ravel().tolist(),
                 "strain_rates": np.asarray(out["strain_rates"][i], float).ravel().tolist() if "strain_rates" in out
                 else [],
                 "last_command": {"stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""}})
            tfs = []
            for name, g in fp.items():
                d = _pose_dict(np.asarray(g, dtype=float))
                tfs.append({"header": header, "child_frame_id": prefix + name,
                            "transform": {"translation": d["position"], "rotation": d["orientation"]}})
            put("/tf", "tf2_msgs/TFMessage", {"transforms": tfs})
            for jn in out["joint_names"]:
                if jn in tnames:
                    W = out["transmitted_wrenches"][i][tnames.index(jn)]
                    put(f"{ns}/joint_wrenches/{topic_name(jn)}", "geometry_msgs/WrenchStamped",
                        {"header": header, "wrench": {"force": dict(zip("xyz", map(float, W[:3]))),
                                                      "torque": dict(zip("xyz", map(float, W[3:])))}})
        w.finish()
    return len(out["members_time"])


def _stamp(msg):
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def articulated_namespaces(messages):
    """Node namespaces with a ``joint_states`` topic in ``messages``."""
    return sorted(t[: -len("/joint_states")] for t in messages if t.endswith("/joint_states"))


def read_node_recording(path, mech, node=None, tf_prefix=None):
    """The run of one twin node recorded in an MCAP file (``node``: its name
    when the file holds several), in the fields of
    :func:`mechanism_scenario.run_mechanism_dynamics`: with the joint,
    member and frame topics (:func:`articulated_run_from_messages`; frames
    on /tf under ``tf_prefix``, default ``<node>/``) when it has them, else
    from the backbone, tip pose and strains every twin node publishes
    (:func:`recording.read_node_run`)."""
    topics = dict.fromkeys(recorded_topics(path))          # decode only the node's state topics below
    found = articulated_namespaces(topics) or node_namespaces(topics)
    if node is not None:
        ns = "/" + node.strip("/")
        if ns not in found:
            raise ValueError(f"{path}: no recorded state of node {ns!r}; found {found}")
    elif len(found) == 1:
        ns = found[0]
    else:
        raise ValueError(f"{path}: " + (f"several twin nodes recorded {found}: choose one with --node"
                                        if found else "no twin state topics (joint_states, or backbone, "
                                                      "tip_pose and strains)"))
    msgs = read_messages(path, [t for t in topics if _state_topic(t, ns)])
    try:
        if f"{ns}/joint_states" in msgs:
            return articulated_run_from_messages(msgs, mech, ns, tf_prefix)
        return read_node_run(msgs, ns, mech)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def _state_topic(topic, ns):
    """True for a topic the run of node ``ns`` is read from (by
    :func:`articulated_run_from_messages` or :func:`read_node_run`)."""
    return topic == "/tf" or topic in [f"{ns}/{s}" for s in ("joint_states",) + STATE_TOPICS] \
        or topic.startswith((f"{ns}/backbones/", f"{ns}/joint_wrenches/"))


def articulated_run_from_messages(msgs, mech, ns, tf_prefix=None):
    """The run of node ``ns`` (``/soft_twin``) in decoded messages {topic:
    [msg, ...]} (from a recording, or received live by rclpy: read by
    attribute), from its joint, member and frame topics (see the module for
    the states kept): time [s] from the first kept stamp,
    joint_names/positions/velocities/efforts, frame_names (the robot's
    frames), frame_positions and frame_poses (from /tf), members_time and
    members ({member: positions, orientations}), strains and section_names,
    and transmitted_names/wrenches of the rigid joints when every kept
    state has them. ``tf_prefix``: the node's (default ``<node>/``)."""
    prefix = tf_prefix if tf_prefix is not None else ns.strip("/") + "/"
    if not msgs.get(f"{ns}/joint_states"):
        raise ValueError(f"no {ns}/joint_states")
    js = {_stamp(m): m for m in msgs[f"{ns}/joint_states"]}
    bb = {}
    for mem in mech.members:
        topic = f"{ns}/backbones/{topic_name(mem.name)}"
        if topic not in msgs:
            raise ValueError(f"no {topic} (the robot's member {mem.name!r}); is it the recorded robot?")
        bb[mem.name] = {_stamp(m): m for m in msgs[topic]}
    fnames = list(mech.frames)
    want = {prefix + n: n for n in fnames}
    tf = {}
    for m in msgs.get("/tf", []):
        for t in m.transforms:
            if t.child_frame_id in want:
                tf.setdefault(_stamp(t), {})[want[t.child_frame_id]] = t.transform
    stamps = set(js)
    for d in bb.values():
        stamps &= set(d)
    stamps = sorted(k for k in stamps if len(tf.get(k, {})) == len(fnames))
    if not stamps:
        raise ValueError(f"no state of {ns} with joint states, every member's backbone and the "
                         f"robot's frames on /tf (prefix {prefix!r}) at one stamp")
    names = list(js[stamps[0]].name)
    st = {_stamp(m): m for m in msgs.get(f"{ns}/strains", [])}
    wr = {jn: {_stamp(m): m for m in msgs.get(f"{ns}/joint_wrenches/{topic_name(jn)}", [])} for jn in names}
    t0 = stamps[0]
    out = {"time": [], "joint_names": names, "joint_positions": [], "joint_velocities": [],
           "joint_efforts": [], "frame_names": fnames, "frame_positions": [], "frame_poses": [],
           "members_time": [], "members": []}
    for k in stamps:
        t = round(1e-9 * (k - t0), 9)        # whole nanoseconds: the nearest float to the decimal time
        j = js[k]
        out["time"].append(t)
        out["joint_positions"].append(list(map(float, j.position)))
        out["joint_velocities"].append(list(map(float, j.velocity)) or [float("nan")] * len(names))
        out["joint_efforts"].append(list(map(float, j.effort)) or [float("nan")] * len(names))
        poses = []
        for n in fnames:
            tr = tf[k][n]
            p, q = tr.translation, tr.rotation
            poses.append(_pose_from_quat([p.x, p.y, p.z], [q.x, q.y, q.z, q.w]).tolist())
        out["frame_poses"].append(poses)
        out["frame_positions"].append([[g[0][3], g[1][3], g[2][3]] for g in poses])
        out["members_time"].append(t)
        members = {}
        for mem in mech.members:
            pa = bb[mem.name][k]
            members[mem.name] = {
                "positions": [[p.position.x, p.position.y, p.position.z] for p in pa.poses],
                "orientations": [[p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
                                 for p in pa.poses]}
        out["members"].append(members)
    soft = mech.tree.soft_joints
    if soft and all(k in st for k in stamps):
        out["section_names"] = [mech.tree.joints[i].name for i in soft]
        out["strains"] = [np.asarray(st[k].strains, float).reshape(-1, 6).tolist() for k in stamps]
    if names and all(k in wr[jn] for jn in names for k in stamps):
        out["transmitted_names"] = list(names)
        out["transmitted_wrenches"] = [
            [[w.x, w.y, w.z, m.x, m.y, m.z] for jn in names
             for w, m in [(wr[jn][k].wrench.force, wr[jn][k].wrench.torque)]] for k in stamps]
    return out
