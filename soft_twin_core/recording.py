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
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    out = {}
    try:
        fh = open(path, "rb")
    except OSError as e:
        raise ValueError(f"cannot read the recording {path!r}: {e.strerror or e}") from None
    with fh:
        try:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for _, channel, _, decoded in reader.iter_decoded_messages(topics=topics, log_time_order=True):
                out.setdefault(channel.topic, []).append(decoded)
        except Exception as e:       # the mcap library raises its own error types
            raise ValueError(f"{path}: not a readable MCAP recording ({type(e).__name__}: {e})") from None
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
