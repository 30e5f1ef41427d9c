"""Compile the engine's kernels once and leave them in numba's disk cache.

``python -m soft_twin_core.warmup`` (run by ``make setup``) exercises every
compiled pass (kinematics, inverse dynamics with loads, mass matrix,
articulated-body factorisation and solve, static tangent, tendons, the
integrator's Newton step, the statics Newton, the IK's bounded least
squares, exponential and Cayley sections) on a tiny soft
arm on a rigid joint, so that a new process starts in about a second instead
of compiling for tens of seconds. Prints what it took.
"""

import sys
import time

import numpy as np

from soft_twin_core.engine.kernels._caches import STAMP, kernel_digest, kernel_sources


def tiny_models():
    """A 2-section tendon arm of each kinematic map (the classic schema)."""
    from soft_twin_core.robot.model import model_from_dict
    out = []
    for kmap in ("exponential", "cayley"):
        out.append(model_from_dict({
            "name": f"warmup_{kmap}", "kinematic_map": kmap, "segments": [{
                "length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
                "material": {"youngs_modulus": 1e6, "poisson_ratio": 0.5, "density": 1000, "viscosity": 10.0}}],
            "actuators": [{"name": "t", "type": "tendon", "offset": [0.005, 0.0]}]}))
    return out


# The parts, in the order one process compiles them: "passes" first, the
# passes nearly every kernel links (numba compiles a callee once and links
# its code into each caller's library).
PARTS = ("passes", "leaves", "rods", "mechanism", "contact", "basis", "ik")

# Side by side (numba compiles on one core, and its cache is per function):
# one lane a process. This one compiles the passes, then what the rods, the
# mechanisms and the IK add; a side process meanwhile compiles what links no
# pass (the contact law's pairs, the bounded least squares), then waits
# until the passes are cached (NEEDS) and compiles the contact step (which
# also takes constraint rows) and the variable-strain step. Cold on a 2-core
# machine, the two lanes at once: passes 23 s, rods 13 s, mechanism 5 s, ik
# 8 s | leaves 19 s, (waits 4 s), contact 22 s, basis 4 s: 50 s in all, in a
# fast phase of the machine (each kernel that steps costs 4-6 s: numba links
# the passes it calls into its library and optimises them again there).
LANES = (("passes", "rods", "mechanism", "ik"), ("leaves", "contact", "basis"))
NEEDS = {"rods": "passes", "mechanism": "passes", "contact": "passes", "basis": "passes", "ik": "rods"}

# How long a side lane waits for a part another process compiles before it
# compiles that part's kernels itself [s].
WAIT_S = 300.0


def run(parts=PARTS, marks=None):
    """Exercise the kernels of ``parts`` (in PARTS's order): "passes" (a
    pinned tree's statics: the forward pass, RNEA, the tangents, the
    actuation, the constraints), "leaves" (the contact law's pairs, the
    bounded least squares), "rods" (the tiny arms' statics, dynamics and
    scenario runs), "mechanism" (the pinned tree's dynamics and outputs),
    "contact" (an arm against four obstacles, statics and dynamics),
    "basis" (a variable-strain arm's compiled dynamic step), "ik"
    (RNEA's derivatives, the actuation IK). ``marks``: a directory where
    each part done leaves a file of its name (all of them, when one fails),
    and where a part first waits for the one it NEEDS when another process
    compiles that one."""
    from pathlib import Path
    runs = {"passes": tiny_pass_runs, "leaves": tiny_leaf_runs, "rods": tiny_rod_runs,
            "mechanism": tiny_mechanism_run, "contact": tiny_contact_run, "basis": tiny_basis_run,
            "ik": tiny_ik_runs}
    try:
        for part in PARTS:
            if part not in parts:
                continue
            if marks is not None and NEEDS.get(part) not in (None, *parts):
                _wait_for(Path(marks) / NEEDS[part])
            t0 = time.perf_counter()
            runs[part]()
            if marks is not None:
                (Path(marks) / part).touch()
            print(f"part {part}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    finally:        # a failure marks the rest too: no other lane waits WAIT_S for a part that will not come
        if marks is not None:
            for part in parts:
                (Path(marks) / part).touch()


def _wait_for(mark):
    """Until file ``mark`` exists, for WAIT_S at most, or until this
    process's parent is gone (then the part compiles what it needs)."""
    import os
    parent, t0 = os.getppid(), time.perf_counter()
    while not mark.exists() and time.perf_counter() - t0 < WAIT_S and os.getppid() == parent:
        time.sleep(0.05)


def tiny_pass_runs():
    """The pinned tree's statics (the KKT Newton calls the residual pass:
    forward pass, RNEA, actuation; the tangents; the constraints' frames)
    and the mass matrix: the passes every step and solver links."""
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.engine.workspace import Workspace
    from soft_twin_core.solve.constrained import solve_equilibrium
    mech = _pinned_tree()
    solve_equilibrium(mech, positions={"j": 0.01})
    alg.crba(mech.tree, Workspace(mech.tree), mech.tree.q0)


def tiny_leaf_runs():
    """What links no pass: the contact law's pairs at rest and over a step
    (an obstacle of each kind, friction, torsion, a moving one) and the
    bounded least squares of the IK."""
    from soft_twin_core.engine.contact import ContactPoints, contact_forces, moved, step_contact_forces
    from soft_twin_core.planning import planner as pl
    from soft_twin_core.robot.obstacles import obstacles_from_list
    obstacles = tuple(obstacles_from_list(_contact_dict()["obstacles"]))
    n = 3
    points = ContactPoints(np.zeros(n, np.int64), np.zeros(n), np.full(n, 0.01), np.full(n, 0.01),
                           np.full(n, 1e6), ("arm",) * n, np.zeros(n))
    p = np.array([[0.0, 0.0, -0.005], [0.1, 0.0, 0.19], [0.1, -0.16, 0.0]])
    contact_forces(points, obstacles, p)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3))
    step_contact_forces(points, obstacles, p, p + 1e-4, p + 5e-5, 1e-3, 0.5, v0=np.zeros((n, 3)),
                        obstacles0=[moved(ob, [0.0, 0.0, 1e-5]) for ob in obstacles],
                        spin=(eye, eye, np.zeros((n, 3))))
    pl.box_lstsq(np.eye(3, 2), np.ones(3), np.zeros(2), np.array([np.inf, 0.5]))


def tiny_rod_runs():
    """The tiny arms of both maps: statics, dynamics (the compiled
    multi-step), the algorithms' passes and the scenario runner's."""
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.engine.loads import Loads, PointLoad
    from soft_twin_core.engine.workspace import Workspace
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    for robot in tiny_models():
        loads = Loads(point=(PointLoad(0.2, (0, 0, -0.01, 0, 0, 0), "world"),
                             PointLoad(0.1, (0, 0.01, 0, 0, 0, 0), "body")))
        mech = from_robot_model(robot)
        solve_equilibrium(mech, {"t": 0.5}, loads=loads)
        MechanismSimulator(mech, 1e-3).step({"t": 0.5}, loads=loads, n=2)
        tree = robot.tree
        ws = Workspace(tree)
        q, v = tree.q0 + 0.01, np.full(tree.nv, 0.1)
        alg.forward_kinematics(tree, ws, q, v, v)
        alg.crba(tree, ws, q)
        alg.forward_dynamics(tree, ws, q, v, np.zeros(tree.nv), alg.make_loads(tree, [0], [0.05], [np.ones(6)],
                                                                                 [True]))
        # the state estimator's and the calibration's passes (issue 14)
        alg.point_jacobian(tree, ws, q, tree.n_joints - 1, 0.05)
        # what the scenario runner adds (backbone, internal wrenches, recorded
        # states): the design studies' workers run it for every case
        from soft_twin_core.files.scenario import run_dynamics, run_statics, scenario_from_dict
        sc = scenario_from_dict({"robot": {"segments": [{
            "length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
            "material": {"youngs_modulus": 1e6, "density": 1000, "viscosity": 10.0}}],
            "kinematic_map": robot.kinematic_map,
            "actuators": [{"name": "t", "type": "tendon", "offset": [0.005, 0.0]}]},
            "actuation": {"t": 0.5}, "loads": [{"s": "tip", "force": [0, 0, -0.01]}]})
        run_statics(sc, 2)
        run_dynamics(sc, 2e-3, 1e-3, 1, points_per_section=2)


def tiny_ik_runs():
    """RNEA's derivatives and the actuation IK (the node's
    ~/inverse_kinematics, the planner): its tip error, sensitivities and
    bounded least squares, position and full pose."""
    from soft_twin_core.engine import algorithms as alg
    from soft_twin_core.engine.workspace import Workspace
    from soft_twin_core.planning import planner as pl
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.solve.constrained import solve_equilibrium
    from soft_twin_core.solve.outputs import state_outputs
    robot = tiny_models()[0]
    tree = robot.tree
    q, v = tree.q0 + 0.01, np.full(tree.nv, 0.1)
    alg.rnea_derivatives(tree, Workspace(tree), q, v, v)
    mech = from_robot_model(robot)
    solver = pl.TipSolver(mech)
    eq = solve_equilibrium(mech, {"t": 0.3})
    target = state_outputs(mech, eq.q, eq.lam, eq.inputs).frames["tip"]
    for with_rot in (False, True):
        solver.with_rot = with_rot
        solver.solve(target, np.zeros(1), None)


def _contact_dict():
    """A 2-section arm among a table, a ball, a post and a block."""
    return {"name": "warmup_contact", "segments": [{
        "length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
        "material": {"youngs_modulus": 1e6, "density": 1000, "viscosity": 10.0}}],
        "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -0.0105], "normal": [0, 0, 1],
                       "friction": 0.3, "damping": 1.0},
                      {"name": "ball", "type": "sphere", "center": [0.1, 0, 0.2], "radius": 0.01},
                      {"name": "post", "type": "capsule", "from": [0.1, 0.2, 0], "to": [0.1, 0.2, 0.1],
                       "radius": 0.01},
                      {"name": "block", "type": "box", "center": [0.1, -0.2, 0], "size": [0.1, 0.1, 0.1]}]}


def tiny_contact_run():
    """A 2-section arm on a table, a ball, a post and a block (issue 27):
    the contact law's kernels in statics and in dynamics, friction and a
    moving obstacle included."""
    from soft_twin_core.engine.contact import moved, transition_step
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import model_from_dict
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    d = _contact_dict()
    mech = from_robot_model(model_from_dict(d), d)
    solve_equilibrium(mech)
    sim = MechanismSimulator(mech, 1e-3)
    sim.step(n=2)
    sim.step(obstacles=[moved(ob, [0.0, 0.0, 1e-5]) for ob in mech.obstacles])
    transition_step(np.zeros((1, 3)), np.ones((1, 3)), np.ones(1))     # the Python (KKT) step's line search


def tiny_basis_run():
    """A 3-section arm on a Legendre basis of order 1: the compiled step
    in the basis's coordinates (reduced_step) and its Newton matrix."""
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import model_from_dict
    from soft_twin_core.solve.constrained import MechanismSimulator
    mech = from_robot_model(model_from_dict({"name": "warmup_basis", "segments": [{
        "length": 0.2, "sections": 3, "cross_section": {"shape": "solid_circle", "radius": 0.01},
        "material": {"youngs_modulus": 1e6, "density": 1000, "viscosity": 10.0},
        "strain_basis": {"type": "legendre", "order": 1}}]}))
    MechanismSimulator(mech, 1e-3).step(n=2)


def _pinned_tree():
    """A soft member on a position-controlled revolute joint, its tip pinned
    to the world."""
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    return mechanism_from_dict({"name": "warmup_tree", "bodies": [
        {"name": "link", "type": "link", "mass": 0.1, "inertia": [1e-4, 1e-4, 1e-4, 0, 0, 0],
         "joint": {"name": "j", "type": "revolute", "axis": [0, 0, 1], "control": "position"}},
        {"name": "arm", "type": "member", "parent": "link", "segments": [{
            "length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
            "material": {"youngs_modulus": 1e6, "density": 1000, "viscosity": 10.0}}]}],
        "constraints": [{"name": "pin", "type": "pinned", "frame": "arm_tip", "to": "world"}]})


def tiny_mechanism_run():
    """The pinned tree's statics, outputs and dynamics: the articulated
    robots' passes (constraint frames, the compiled closed-chain step,
    outputs)."""
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    from soft_twin_core.solve.outputs import state_outputs
    mech = _pinned_tree()
    eq = solve_equilibrium(mech, positions={"j": 0.01})
    state_outputs(mech, eq.q, eq.lam, eq.inputs)
    sim = MechanismSimulator(mech, 1e-3, q=eq.q)
    sim.step(positions={"j": 0.01}, n=2)
    state_outputs(mech, sim.q, sim.lam, sim.inputs, sim.v, sim.a, sim.ws)


def copy_caches(src, dst):
    """Give the copy of this package at ``dst`` (the one installed in a
    venv) the kernel caches of the one at ``src`` (the checkout, warmed up),
    when their kernels' sources are identical: numba (0.68) stamps a cache
    with its source file's content hash, so a cache serves an identical file
    anywhere, and the installed copy loads in seconds instead of compiling
    for minutes. Its own caches are replaced, and the stamp of
    :func:`purge_stale_caches` with them. Returns the number of cache files
    copied, or None when the sources differ or ``NUMBA_CACHE_DIR`` moves
    the caches elsewhere (then it compiles its own)."""
    import os
    import shutil
    from pathlib import Path
    src, dst = Path(src), Path(dst)
    if os.environ.get("NUMBA_CACHE_DIR") or kernel_digest(src) != kernel_digest(dst):
        return None
    n = 0
    for d in sorted({f.parent / "__pycache__" for f in kernel_sources(src)}):
        target = dst / d.relative_to(src)
        target.mkdir(parents=True, exist_ok=True)
        for old in list(target.glob("*.nbi")) + list(target.glob("*.nbc")):
            old.unlink()
        for f in list(d.glob("*.nbi")) + list(d.glob("*.nbc")):
            shutil.copyfile(f, target / f.name)
            n += 1
    stamp = src / "__pycache__" / STAMP
    if stamp.is_file():
        (dst / "__pycache__").mkdir(exist_ok=True)
        shutil.copyfile(stamp, dst / "__pycache__" / stamp.name)
    return n


def install_caches(dst):
    """Give the copy of this package at ``dst`` (an install space's, e.g.
    colcon's) its kernel caches: this copy's when its kernels' sources are
    the same (:func:`copy_caches`: seconds), then a warm-up of that copy in
    a process of its own (``python -m soft_twin_core.warmup`` with it first
    on the path), which loads them, or compiles what is missing or stale
    there. Returns that process's exit code."""
    import os
    import subprocess
    from pathlib import Path
    src, dst = Path(__file__).resolve().parent, Path(dst).resolve()
    if src != dst:                 # (a symlinked install is this copy: warmed in place)
        n = copy_caches(src, dst)
        print(f"soft_twin_core kernel caches: {'sources differ, none' if n is None else n} copied to {dst}",
              file=sys.stderr)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(dst.parent)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return subprocess.run([sys.executable, "-m", "soft_twin_core.warmup"], cwd=dst.parent, env=env).returncode


def purge_stale_caches(root=None):
    """Delete every kernel cache of this package when a source a kernel
    depends on (:func:`kernel_sources`) changed since the last warm-up;
    returns True if it did.

    numba checks a cached kernel against its own file's timestamp only: a
    kernel whose callee in another file changed (linked or inlined into it)
    would load the old machine code. A hash of the kernels' sources, kept
    beside the caches, catches that (and an upgrade installed over an old
    ``__pycache__``); a change elsewhere in the package (the solvers' Python
    layers, the files, the views) keeps the caches. ``NUMBA_CACHE_DIR``: its
    copy of this package's tree is purged too."""
    import os
    from pathlib import Path
    root = Path(__file__).resolve().parent if root is None else Path(root)
    digest = kernel_digest(root)
    stamp = root / "__pycache__" / STAMP
    if stamp.is_file() and stamp.read_text().strip() == digest:
        return False
    dirs = [root]
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if cache_dir:
        dirs += _user_cache_dirs(root, Path(cache_dir))
    for d in dirs:
        for f in list(d.rglob("*.nbi")) + list(d.rglob("*.nbc")):
            f.unlink(missing_ok=True)
    stamp.parent.mkdir(exist_ok=True)
    stamp.write_text(digest + "\n")
    return True


def _user_cache_dirs(root, cache_dir):
    """The directories under ``NUMBA_CACHE_DIR`` that hold the caches of the
    sources under ``root``: numba names one per source directory, by its
    name and a hash of its absolute path (``<name>_<sha1>``), so the caches
    of another copy of the package (the venv's) are left alone."""
    from numba.core.caching import _CacheLocator
    src_dirs = {f.resolve().parent for f in root.rglob("*.py")}
    return [cache_dir / _CacheLocator.get_suitable_cache_subpath(str(d / "_.py")) for d in sorted(src_dirs)]


def compile_side_by_side(lanes=LANES):
    """Compile the parts of ``lanes`` at once: the first lane here, the
    next ones each in a process of its own (``python -m
    soft_twin_core.warmup --parts P,Q --marks DIR``, this copy of the
    package first on its path), as many as the cores this process may use
    (the lanes beyond them here too). The parts leave marks in a shared
    temporary directory, and wait there for the part they need (NEEDS). A
    lane whose process fails is named with its output and left to the
    caller's :func:`run`, which compiles whatever is not cached. Returns
    the number of processes started."""
    import os
    import shutil
    import subprocess
    import tempfile
    from pathlib import Path
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    side = list(lanes[1:max(cores, 1)])
    here = tuple(p for lane in [lanes[0], *lanes[1 + len(side):]] for p in lane)
    marks = tempfile.mkdtemp(prefix="soft_twin_warmup_")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1])] +
                                        ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    procs = [subprocess.Popen([sys.executable, "-m", "soft_twin_core.warmup", "--parts", ",".join(lane),
                               "--marks", marks], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True) for lane in side]
    try:
        run(here, marks if procs else None)
    finally:
        for p, lane in zip(procs, side):
            out, _ = p.communicate()
            if p.returncode:
                print(f"warm-up of parts {','.join(lane)} failed (exit {p.returncode}); compiling them here:\n"
                      f"{out[-2000:]}", file=sys.stderr)
            else:
                sys.stderr.write(out)
        shutil.rmtree(marks, ignore_errors=True)
    return len(procs)


def main(argv=None):
    """``python -m soft_twin_core.warmup [--copy-to DIR | --install-to DIR | --parts P,Q [--marks DIR]]``:
    compile (or load) every kernel, after a purge the parts side by side
    (:func:`compile_side_by_side`); with ``--copy-to``, then give the copy
    of the package at DIR these caches (:func:`copy_caches`); with
    ``--install-to``, give the copy at DIR its caches without compiling
    this one's (:func:`install_caches`: the colcon build's step); with
    ``--parts``, those parts only (a side lane; ``--marks``: see
    :func:`run`)."""
    argv = sys.argv[1:] if argv is None else argv
    t0 = time.perf_counter()
    if argv[:1] == ["--copy-to"] and len(argv) == 2:
        from pathlib import Path
        run()                                      # (the caches complete first)
        n = copy_caches(Path(__file__).resolve().parent, argv[1])
        print(f"soft_twin_core kernel caches: {'sources differ, none' if n is None else n} copied to {argv[1]}",
              file=sys.stderr)
        return 0
    if argv[:1] == ["--install-to"] and len(argv) == 2:
        return install_caches(argv[1])
    if argv[:1] == ["--parts"] and len(argv) in (2, 4) and set(argv[1].split(",")) <= set(PARTS) and (
            len(argv) == 2 or argv[2] == "--marks"):
        run(tuple(argv[1].split(",")), argv[3] if len(argv) == 4 else None)
        return 0
    if argv:
        print("usage: python -m soft_twin_core.warmup [--copy-to DIR | --install-to DIR | "
              f"--parts P[,Q...] [--marks DIR]]  (parts: {', '.join(PARTS)})", file=sys.stderr)
        return 2
    if purge_stale_caches():
        print("soft_twin_core sources changed since the last warm-up: kernel caches cleared", file=sys.stderr)
        compile_side_by_side()
    run()                                          # (loads what the parts compiled; compiles anything left)
    print(f"soft_twin_core kernels compiled and cached in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
