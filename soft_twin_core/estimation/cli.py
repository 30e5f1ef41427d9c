"""``soft-twin-sim calibrate``: the command line of :mod:`calibration`
(argument parsing, robot and data files, the report), apart from the
fitting so that :mod:`calibration_mcap` (which builds the fit's records)
and the fit import each other in one direction only."""

import json
import os
import sys

import numpy as np
import yaml

from soft_twin_core.errors import CalibrationError, CalibrationFailed, ModelError, StaticsError
from soft_twin_core.estimation import mcap_data as cm, sensors as sn
from soft_twin_core.estimation.ekf import parse_directions
from soft_twin_core.estimation.calibration import (_expand, calibrate, calibrate_dynamic, mechanism_of,
                                                   read_csv, write_robot_file)
from soft_twin_core.robot.model import find_file, read_yaml_file, robot_mapping


def add_cli_parser(sub):
    """The ``calibrate`` subcommand of ``soft-twin-sim``."""
    c = sub.add_parser("calibrate", help="fit robot parameters to a recorded static sweep (CSV or MCAP)")
    c.add_argument("robot", help="robot file or example name")
    c.add_argument("--sensors", required=True, help="sensors file (YAML list of pose/marker sensors)")
    c.add_argument("--data", required=True,
                   help="CSV (t, one column per actuator and per position-controlled joint, optional "
                        "efforts of effort-controlled joints, known loads wrench:<point>.fx..mz [N, N m] and "
                        "mass:<point> [kg], <sensor>.x/.y/.z[/.qx..qw]; a header may carry its SI unit, "
                        "'t [s]') or an MCAP recording (ROS 2 bag: commands, known loads and sensor topics, "
                        "see --actuation-topic, --topic)")
    c.add_argument("--fit", required=True,
                   help="comma-separated parameters: youngs_modulus:<segment> (youngs_modulus:<a>+<b>: one "
                        "modulus for both), tendon_offset:<tendon>, payload_mass, sensor_offset:<sensor>:<x|y|z>; "
                        "with --dynamic also viscosity:<segment> and density:<segment> (not payload_mass); "
                        "'youngs_modulus', 'viscosity', 'density' or 'tendon_offset' alone mean all segments / all "
                        "straight tendons")
    c.add_argument("--holdout-every", type=int, default=4, metavar="K",
                   help="hold out every K-th row to report the error before/after (0: none; default 4)")
    c.add_argument("--sections", type=int,
                   help="sections per segment for the fit, classic robots (default: the robot file's)")
    c.add_argument("--dynamic", action="store_true",
                   help="the rows are a time series from rest under the first row's inputs and loads (column "
                        "t; a release test, a step): fit the parameters by simulating it")
    c.add_argument("--dt", type=float, default=5e-3, help="integrator step for --dynamic [s] (default 0.005)")
    _add_mcap_arguments(c)
    c.add_argument("--settle", type=float, metavar="S",
                   help="MCAP: seconds after each command before the readings are averaged "
                        "(default: the second half of each hold)")
    c.add_argument("--output", "-o", help="write the calibrated robot file here")
    c.add_argument("--sensors-output", help="write the calibrated sensors file here")
    e = sub.add_parser("estimate", help="run the state estimator over a recorded time series (CSV or MCAP): "
                                        "estimates, innovation statistics and a figure")
    e.add_argument("robot", help="robot file or example name")
    e.add_argument("--sensors", required=True, help="sensors file (YAML list of pose/marker sensors)")
    e.add_argument("--data", required=True,
                   help="CSV (as for calibrate, with its column t) or an MCAP recording of the twin's and the "
                        "estimator's topics (as for calibrate --dynamic)")
    e.add_argument("--wrench", choices=("payload", "force", "wrench"),
                   help="also estimate an unknown tip load: a payload mass [kg], a force or a wrench")
    e.add_argument("--force-directions", metavar="X,Y,Z[;X,Y,Z]",
                   help="with --wrench force: the world directions the force lies along, e.g. '0,0,1' (a "
                        "contact's normal) or '0,1,0;0,0,1' (across an arm along x); default: all three axes")
    e.add_argument("--dt", type=float, help="the filter's step [s] (default: the rows' median spacing)")
    e.add_argument("--sections", type=int, help="sections per segment, classic robots (default: the robot file's)")
    _add_mcap_arguments(e)
    e.add_argument("--output", "-o", help="write the estimates here as CSV (SI units in the header)")
    e.add_argument("--plot", metavar="FOLDER",
                   help="write the figure FOLDER/estimation.png (and .svg; --style paper: PDF) here")
    e.add_argument("--style", default="screen", choices=("screen", "paper", "paper-wide"),
                   help="figure style (default screen)")
    return c


def _add_mcap_arguments(c):
    """The topic options of an MCAP record (soft_twin_core.estimation.mcap_data)."""
    c.add_argument("--actuation-topic", default="/soft_twin/actuation",
                   help="MCAP: topic of the actuation commands (default /soft_twin/actuation)")
    c.add_argument("--joint-command-topic", default="/soft_twin/joint_commands",
                   help="MCAP: topic of the position commands of the position-controlled joints "
                        "(sensor_msgs/JointState; default /soft_twin/joint_commands)")
    c.add_argument("--point-wrench-topic", default="/soft_twin/point_wrench_command",
                   help="MCAP: topic of the known loads on the robot's points (soft_twin/PointWrench; "
                        "default /soft_twin/point_wrench_command)")
    c.add_argument("--tip-wrench-topic", default="/soft_twin/tip_wrench_command",
                   help="MCAP: topic of the known load on the tip (geometry_msgs/WrenchStamped; "
                        "default /soft_twin/tip_wrench_command)")
    c.add_argument("--base-frame", default="base_link",
                   help="MCAP: the base frame of the recorded loads' frame_id (a dead load; default base_link)")
    c.add_argument("--measurements-ns", default="/soft_twin_estimator",
                   help="MCAP: namespace of the estimator's measurement topics <ns>/measurements/poses, "
                        "/pose, /position (default /soft_twin_estimator)")
    c.add_argument("--topic", action="append", default=[], metavar="SENSOR=TOPIC",
                   help="MCAP: a sensor's own topic (PoseStamped, PoseWithCovarianceStamped, "
                        "TransformStamped or PointStamped); repeatable")




def estimate_run(args):
    """The replay of ``soft-twin-sim estimate`` (the figure is drawn by the
    command line above, :mod:`soft_twin_core.cli`): (EstimationRun, the
    JSON report with the CSV written), or (None, exit status 2) for a bad
    argument or file (named on stderr)."""
    from soft_twin_core.estimation.replay import estimate_recording  # here: the calibrate command does not need it
    try:
        if args.sections is not None and args.sections < 1:
            raise CalibrationError(f"--sections must be >= 1, got {args.sections}")
        path = find_file(args.robot, "robots")
        robot_dict = robot_mapping(read_yaml_file(path, ModelError, "robot file"), f"robot file {path}")
        mech = mechanism_of(robot_dict, args.sections, os.path.dirname(os.path.abspath(path)))
        sensors = sn.load_sensors(args.sensors, mech)
        if cm.is_mcap(args.data):
            args.dynamic = True                           # (a time series)
            rec, _ = _read_mcap(args, mech, sensors)
        else:
            rec = read_csv(args.data, mech, sensors)
        options = {}
        if args.force_directions is not None:
            options["force_directions"] = parse_directions(args.force_directions, "--force-directions")
        run = estimate_recording(mech, sensors, rec, dt=args.dt, wrench=args.wrench, **options)
    except (CalibrationError, ModelError, ValueError) as e:
        print(f"soft-twin-sim estimate: {e}", file=sys.stderr)
        return None, 2
    report = run.summary()
    if args.output:
        head, body = run.rows()
        np.savetxt(args.output, body, delimiter=",", header=",".join(head), comments="", fmt="%.9g")
        report["output"] = args.output
    return run, report


def cli_main(args):
    """Run ``soft-twin-sim calibrate``; JSON report on stdout, the table on
    stderr. Exit 0, or 2 for a bad argument or file (named on stderr), 3 if
    a statics solve fails."""
    try:
        if args.sections is not None and args.sections < 1:
            raise CalibrationError(f"--sections must be >= 1, got {args.sections}")
        if args.holdout_every < 0:
            raise CalibrationError(f"--holdout-every must be >= 0, got {args.holdout_every}")
        path = find_file(args.robot, "robots")
        robot_dict = robot_mapping(read_yaml_file(path, ModelError, "robot file"), f"robot file {path}")
        base_dir = os.path.dirname(os.path.abspath(path))
        mech = mechanism_of(robot_dict, args.sections, base_dir)
        sensors = sn.load_sensors(args.sensors, mech)
        mcap_report = None
        if cm.is_mcap(args.data):                      # an MCAP recording of the node
            rec, mcap_report = _read_mcap(args, mech, sensors)
        else:
            rec = read_csv(args.data, mech, sensors)
        names = [n.strip() for n in args.fit.split(",") if n.strip()]
        if not names:
            raise CalibrationError("--fit: no parameter given")
        names = _expand(names, robot_dict)
        if args.dynamic:
            if not (np.isfinite(args.dt) and args.dt > 0):
                raise CalibrationError(f"--dt must be a positive step in s, got {args.dt}")
            res = calibrate_dynamic(robot_dict, sensors, rec, names, dt=args.dt, n_sections=args.sections,
                                    base_dir=base_dir)
        else:
            res = calibrate(robot_dict, sensors, rec, names, holdout_every=args.holdout_every,
                            n_sections=args.sections, base_dir=base_dir)
    except (CalibrationError, ModelError, ValueError) as e:
        print(f"soft-twin-sim calibrate: {e}", file=sys.stderr)
        return 2
    except (StaticsError, CalibrationFailed) as e:
        print(f"soft-twin-sim calibrate: {e}", file=sys.stderr)
        return 3
    print(res.table(), file=sys.stderr)
    report = {"parameters": {n: {"nominal": float(a), "fitted": float(b), "std": float(c), "ci95": float(e)}
                             for n, a, b, c, e in zip(res.names, res.nominal, res.values, res.std, res.ci95)},
              "residual_sigma": res.residual_sigma, "n_residuals": res.n_residuals,
              "heldout": res.heldout, "payload_mass_kg": res.payload_mass,
              "rows": len(rec), "known_loads": [f"{p} ({axes})" for p, axes in rec.wrenches],
              "warnings": list(getattr(res, "warnings", []))}
    if getattr(res, "correlation", None) is not None:
        report["correlation"] = {"parameters": list(res.names),
                                 "matrix": [[float(x) for x in row] for row in res.correlation]}
    if mcap_report is not None:
        report["recording"] = mcap_report
    if args.output:
        lines = [f"Calibrated by soft-twin-sim calibrate from {args.data} ({len(rec)} rows)."]
        lines += [f"{n}: {b:.6g} +- {e:.3g} (95 %), nominal {a:.6g}"
                  for n, a, b, e in zip(res.names, res.nominal, res.values, res.ci95)]
        if res.heldout:
            lines.append(f"held-out tip error RMS {res.heldout['tip_rms_before_m']:.4g} m before, "
                         f"{res.heldout['tip_rms_after_m']:.4g} m after")
        write_robot_file(args.output, res.robot_dict, "\n".join(lines))
        report["robot_file"] = args.output
    if args.sensors_output:
        with open(args.sensors_output, "w") as fh:
            yaml.safe_dump({"sensors": sn.sensors_to_list(res.sensors)}, fh, sort_keys=False,
                           default_flow_style=None)
        report["sensors_file"] = args.sensors_output
    print(json.dumps(report, indent=1))
    return 0


def _read_mcap(args, model, sensors):
    """(Recording, report) of ``--data FILE.mcap`` with the topic flags."""
    topics = {}
    for item in args.topic:
        name, sep, topic = item.partition("=")
        if not sep or not name or not topic.startswith("/"):
            raise CalibrationError(f"--topic: expected SENSOR=/topic, got {item!r}")
        topics[name] = topic
    kw = dict(actuation_topic=args.actuation_topic, joint_command_topic=args.joint_command_topic,
              measurements_ns=args.measurements_ns, topics=topics, point_wrench_topic=args.point_wrench_topic,
              tip_wrench_topic=args.tip_wrench_topic, base_frame=args.base_frame)
    if args.dynamic:
        return cm.read_time_series(args.data, model, sensors, **kw)
    return cm.read_static_sweep(args.data, model, sensors, settle_s=args.settle, **kw)
