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


# The parts, the longest compile first, compiled side by side (numba compiles
# on one core, and its cache is per function). Cold, one at a time on a
# quiet 2-core machine: contact 155 s, rods 67 s, mechanism 30 s.
PARTS = ("contact", "rods", "mechanism")


def run(parts=PARTS):
    """Exercise the kernels of ``parts``: "contact" (an arm against four
    obstacles, statics and dynamics), "rods" (the tiny arms' passes,
    statics, dynamics, scenario runs and the IK), "mechanism" (a tree with a
    closed loop and position control)."""
    if "rods" in parts:
        tiny_rod_runs()
    if "mechanism" in parts:
        tiny_mechanism_run()
    if "contact" in parts:
        tiny_contact_run()


def tiny_rod_runs():
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
        if robot.kinematic_map == "exponential":
            alg.rnea_derivatives(tree, ws, q, v, v)
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
    # the actuation IK (node's ~/inverse_kinematics, the planner): its tip
    # error, sensitivities and bounded least squares, position and full pose
    from soft_twin_core.planning import planner as pl
    from soft_twin_core.solve.outputs import state_outputs
    mech = from_robot_model(tiny_models()[0])
    solver = pl.TipSolver(mech)
    eq = solve_equilibrium(mech, {"t": 0.3})
    target = state_outputs(mech, eq.q, eq.lam, eq.inputs).frames["tip"]
    for with_rot in (False, True):
        solver.with_rot = with_rot
        solver.solve(target, np.zeros(1), None)
    pl.box_lstsq(np.eye(3, 2), np.ones(3), np.zeros(2), np.array([np.inf, 0.5]))


def tiny_contact_run():
    """A 2-section arm on a table, a ball, a post and a block (issue 27):
    the contact law's kernels in statics and in dynamics, friction and a
    moving obstacle included."""
    from soft_twin_core.engine.contact import moved, transition_step
    from soft_twin_core.robot.mechanism import from_robot_model
    from soft_twin_core.robot.model import model_from_dict
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    d = {"name": "warmup_contact", "segments": [{
        "length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
        "material": {"youngs_modulus": 1e6, "density": 1000, "viscosity": 10.0}}],
        "obstacles": [{"name": "table", "type": "plane", "point": [0, 0, -0.0105], "normal": [0, 0, 1],
                       "friction": 0.3, "damping": 1.0},
                      {"name": "ball", "type": "sphere", "center": [0.1, 0, 0.2], "radius": 0.01},
                      {"name": "post", "type": "capsule", "from": [0.1, 0.2, 0], "to": [0.1, 0.2, 0.1],
                       "radius": 0.01},
                      {"name": "block", "type": "box", "center": [0.1, -0.2, 0], "size": [0.1, 0.1, 0.1]}]}
    mech = from_robot_model(model_from_dict(d), d)
    solve_equilibrium(mech)
    sim = MechanismSimulator(mech, 1e-3)
    sim.step(n=2)
    sim.step(obstacles=[moved(ob, [0.0, 0.0, 1e-5]) for ob in mech.obstacles])
    transition_step(np.zeros((1, 3)), np.ones((1, 3)), np.ones(1))     # the Python (KKT) step's line search


def tiny_mechanism_run():
    """A soft member on a position-controlled revolute joint, its tip pinned
    to the world: the articulated robots' passes (constraint frames, KKT
    statics and dynamics, outputs)."""
    from soft_twin_core.robot.mechanism import mechanism_from_dict
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    from soft_twin_core.solve.outputs import state_outputs
    mech = mechanism_from_dict({"name": "warmup_tree", "bodies": [
        {"name": "link", "type": "link", "mass": 0.1, "inertia": [1e-4, 1e-4, 1e-4, 0, 0, 0],
         "joint": {"name": "j", "type": "revolute", "axis": [0, 0, 1], "control": "position"}},
        {"name": "arm", "type": "member", "parent": "link", "segments": [{
            "length": 0.2, "sections": 2, "cross_section": {"shape": "solid_circle", "radius": 0.01},
            "material": {"youngs_modulus": 1e6, "density": 1000, "viscosity": 10.0}}]}],
        "constraints": [{"name": "pin", "type": "pinned", "frame": "arm_tip", "to": "world"}]})
    eq = solve_equilibrium(mech, positions={"j": 0.01})
    state_outputs(mech, eq.q, eq.lam, eq.inputs)
    sim = MechanismSimulator(mech, 1e-3, q=eq.q)
    sim.step(positions={"j": 0.01}, n=2)
    state_outputs(mech, sim.q, sim.lam, sim.inputs, sim.v, sim.a, sim.ws)


def _top_level_imports(f, root):
    """The package's source files that file ``f`` imports at its top level
    (``import soft_twin_core.x``, ``from soft_twin_core.x import y``: x's file,
    and y's when y is a module)."""
    import ast

    def source(name):
        parts = name.split(".")
        if parts[0] != root.name:
            return None
        p = root.joinpath(*parts[1:])
        for cand in (p.with_suffix(".py"), p / "__init__.py"):
            if cand.is_file():
                return cand
        return None
    out = set()
    for node in ast.parse(f.read_text()).body:
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        out |= {s for s in map(source, names) if s is not None}
    return out


def kernel_sources(root):
    """The source files whose change can change a compiled kernel: those
    that import numba or the package's jit decorators (``_jit...``), and
    every file they import at their top level, transitively (a kernel bakes
    in the module globals it reads, and links the kernels it calls). A
    jitted function cannot import, so imports inside functions do not
    count; the warm-up driver (this file) is no kernel."""
    import ast
    from pathlib import Path
    root = Path(root)

    def is_kernel_file(f):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "numba" for a in node.names):
                return True
            if isinstance(node, ast.ImportFrom) and node.module and (
                    node.module.split(".")[0] == "numba" or any(a.name.startswith("_jit") for a in node.names)):
                return True
        return False
    todo = [f for f in sorted(root.rglob("*.py")) if f.name != "warmup.py" and is_kernel_file(f)]
    seen = set(todo)
    while todo:
        for g in _top_level_imports(todo.pop(), root):
            if g not in seen:
                seen.add(g)
                todo.append(g)
    return sorted(seen)


def _kernel_digest(root):
    """The hash of the kernels' sources under ``root`` (paths and contents)."""
    import hashlib
    h = hashlib.sha256()
    for f in kernel_sources(root):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


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
    if os.environ.get("NUMBA_CACHE_DIR") or _kernel_digest(src) != _kernel_digest(dst):
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
    stamp = src / "__pycache__" / "soft_twin_kernels.sha256"
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
    digest = _kernel_digest(root)
    stamp = root / "__pycache__" / "soft_twin_kernels.sha256"
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


def compile_side_by_side(parts=PARTS):
    """Compile ``parts`` at once: the first ones each in a process of its
    own (``python -m soft_twin_core.warmup --part P``, this copy of the
    package first on its path), one fewer than the cores this process may
    use, and the rest in this process meanwhile. A part whose process fails
    is left to the caller's :func:`run`, which compiles whatever is not
    cached. Returns the number of processes started."""
    import os
    import subprocess
    from pathlib import Path
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    others = list(parts[:min(cores - 1, len(parts) - 1)])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1])] +
                                        ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    procs = [subprocess.Popen([sys.executable, "-m", "soft_twin_core.warmup", "--part", p], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for p in others]
    try:
        run(tuple(p for p in parts if p not in others))
    finally:
        for p, name in zip(procs, others):
            out, _ = p.communicate()
            if p.returncode:
                print(f"warm-up of part {name} failed (exit {p.returncode}); compiling it here:\n{out[-2000:]}",
                      file=sys.stderr)
    return len(procs)


def main(argv=None):
    """``python -m soft_twin_core.warmup [--copy-to DIR | --install-to DIR | --part P]``:
    compile (or load) every kernel, after a purge the parts side by side
    (:func:`compile_side_by_side`); with ``--copy-to``, then give the copy
    of the package at DIR these caches (:func:`copy_caches`); with
    ``--install-to``, give the copy at DIR its caches without compiling
    this one's (:func:`install_caches`: the colcon build's step); with
    ``--part``, that part only (the side process)."""
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
    if argv[:1] == ["--part"] and len(argv) == 2 and argv[1] in PARTS:
        run((argv[1],))
        return 0
    if argv:
        print(f"usage: python -m soft_twin_core.warmup [--copy-to DIR | --install-to DIR | --part {'|'.join(PARTS)}]",
              file=sys.stderr)
        return 2
    if purge_stale_caches():
        print("soft_twin_core sources changed since the last warm-up: kernel caches cleared", file=sys.stderr)
        compile_side_by_side()
    run()                                          # (loads what the parts compiled; compiles anything left)
    print(f"soft_twin_core kernels compiled and cached in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
