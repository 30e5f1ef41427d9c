"""MCAP recordings (ROS 2 bag format) of soft articulated robots: a
simulated run written as the twin node publishes it, and a recording (the
node's ``record_file`` or :func:`write_articulated_mcap`) read back into
the run fields that :mod:`mechanism_plots` and :mod:`mechanism_scene` draw.

Topics (``/<node>/...`` as the node names them)::

    joint_states            sensor_msgs/JointState   positions, velocities, efforts of the rigid joints
    backbones/<member>      geometry_msgs/PoseArray  the member's section-boundary poses
    backbone                geometry_msgs/PoseArray  the main member's (outputs.main_member)
    tip_pose                geometry_msgs/PoseStamped
    strains                 soft_twin/Strains        every soft section, tree order
    joint_wrenches/<joint>  geometry_msgs/WrenchStamped (the node: only while subscribed)
    /tf                     tf2_msgs/TFMessage       <node>/<frame> of every named frame

A state is one header stamp; the read-back keeps the stamps that have the
joint states, every member's backbone and the frames on /tf (the node
sends /tf at ``tf_rate_hz``, so a node recording reads back at that rate).
No ROS import: ``mcap`` and ``mcap-ros2-support``.
"""

import re

import numpy as np

from .recording import _DEFS, _DEPS, _SEP, _pose_dict, read_messages

_MORE_DEFS = {
    "sensor_msgs/JointState": "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
                              "float64[] effort\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "geometry_msgs/Wrench": "Vector3 force\nVector3 torque\n",
    "geometry_msgs/WrenchStamped": "std_msgs/Header header\nWrench wrench\n",
}
_MORE_DEPS = {
    "sensor_msgs/JointState": ("std_msgs/Header", "builtin_interfaces/Time"),
    "tf2_msgs/TFMessage": ("geometry_msgs/TransformStamped", "std_msgs/Header", "builtin_interfaces/Time",
                           "geometry_msgs/Transform", "geometry_msgs/Vector3", "geometry_msgs/Quaternion"),
    "geometry_msgs/WrenchStamped": ("std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Wrench",
                                    "geometry_msgs/Vector3"),
}


def topic_name(name):
    """The node's topic token for a user-given name (``soft_twin.node._topic_name``)."""
    t = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return t if t and not t[0].isdigit() else f"_{t}"


def _definition(name):
    defs, deps = {**_DEFS, **_MORE_DEFS}, {**_DEPS, **_MORE_DEPS}
    return defs[name] + "".join(f"{_SEP}\nMSG: {d}\n{defs[d]}" for d in deps[name])


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
        from .mechanism import tip_frame as tip_frame_of
        tip_frame = tip_frame_of(mech)
    from .outputs import main_member
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
    from .recording import node_namespaces, read_node_run
    msgs = read_messages(path)
    found = articulated_namespaces(msgs) or node_namespaces(msgs)
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
    try:
        if f"{ns}/joint_states" in msgs:
            return articulated_run_from_messages(msgs, mech, ns, tf_prefix)
        return read_node_run(msgs, ns, mech)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


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
