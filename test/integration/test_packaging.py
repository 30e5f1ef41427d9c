"""Packaging checks: the ROS-free core stays ROS-free and installs with plain
pip; the ROS package built by `make setup` gives the generated interfaces,
the node package and the commands, from the sources and from the install."""
import os
import re
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CORE = ROOT / "soft_twin_core"
CONSTRAINTS = ROOT / "requirements" / "constraints.txt"

# Modules the core must never import: ROS client library, generated ROS
# types, and the node package (the dependency arrow is soft_twin -> core).
ROS_MODULES = ("rclpy", "rosidl_runtime_py", "rosidl_generator_py", "std_msgs",
               "geometry_msgs", "std_srvs", "builtin_interfaces", "soft_twin")
_IMPORT_RE = re.compile(
    r"^\s*(?:from\s+(?P<from>[\w.]+)\s+import|import\s+(?P<imp>[\w., ]+))", re.M)


def _clean_env(**extra):
    """Environment for a child Python that must not see this venv's ROS set-up."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "LD_LIBRARY_PATH", "VIRTUAL_ENV",
                        "AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH", "PYTHONSAFEPATH",
                        "_ROS_WHEELS_BOOTSTRAP_COMPLETE",
                        # a user's shell: no CPU target chosen yet (this process's kernels chose one), no cache moved
                        "NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES", "NUMBA_CACHE_DIR")}
    env.update(extra)
    return env


def _run(cmd, timeout, **kw):
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)
    assert proc.returncode == 0, (
        f"{cmd} exited {proc.returncode}\n--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


# ---------------------------------------------------------------- core is ROS-free

def test_core_sources_never_import_ros():
    offenders = []
    for path in sorted(CORE.rglob("*.py")):
        for m in _IMPORT_RE.finditer(path.read_text(encoding="utf-8")):
            names = [m.group("from")] if m.group("from") else [
                n.strip().split(" ")[0] for n in m.group("imp").split(",")]
            for name in names:
                if name.split(".")[0] in ROS_MODULES:
                    offenders.append(f"{path.relative_to(ROOT)}: {m.group(0).strip()}")
    assert not offenders, "soft_twin_core imports ROS:\n" + "\n".join(offenders)


def test_importing_core_loads_no_ros_module():
    # a fresh interpreter, from the sources; every submodule is imported
    code = textwrap.dedent(f"""
        import importlib, pkgutil, sys
        import soft_twin_core
        for info in pkgutil.walk_packages(soft_twin_core.__path__, "soft_twin_core."):
            importlib.import_module(info.name)
        bad = sorted(m for m in sys.modules if m.split(".")[0] in {ROS_MODULES!r})
        assert not bad, bad
        print("ok", soft_twin_core.__file__)
    """)
    proc = _run([sys.executable, "-c", code], timeout=300, cwd=ROOT)
    assert str(CORE) in proc.stdout


def readme_python_snippets():
    """The ```python blocks of README.md."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return re.findall(r"^```python\n(.*?)^```", text, re.M | re.S)


def test_readme_snippets_use_no_checkout_paths():
    """The README's Python snippets name example files by name, not by a
    path into the checkout (they must run from any directory)."""
    snippets = readme_python_snippets()
    assert len(snippets) >= 2
    for code in snippets:
        assert "config/" not in code and "../" not in code, code


def test_readme_links_stay_in_the_repository():
    """Every link of the README and the docs pages is an anchor of its page
    or a file (and heading) of the repository; nothing points outside it
    (no URLs, no shared/ material); the conventions document is the
    repository's own and the model's literature is cited."""
    pages = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
    assert len(pages) >= 10

    def anchors(p):
        return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
                for h in re.findall(r"^#+ (.*)$", p.read_text(encoding="utf-8"), re.M)}
    everything = ""
    for page in pages:
        text = page.read_text(encoding="utf-8")
        everything += text
        assert not re.search(r"https?://|www\.", text), page
        assert "shared/" not in text and "slides" not in text.lower() and "DESIGN.md" not in text, page
        for t in re.findall(r"\]\(([^)\s]+)\)", text):
            file, _, anchor = t.partition("#")
            path = (page.parent / file).resolve() if file else page
            assert path.is_relative_to(ROOT) and path.exists(), (page.name, t)
            if anchor and path.suffix == ".md":
                assert anchor in anchors(path), (page.name, t)
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "(docs/CONVENTIONS.md)" in readme and len(readme.splitlines()) <= 300
    conventions = (ROOT / "docs" / "CONVENTIONS.md").read_text(encoding="utf-8")
    assert "shared/" not in conventions and "[linear; angular]" in conventions
    for cite in ("Grazioso, Di Gironimo & Siciliano", "Renda et al. 2018", "Simo & Vu-Quoc",
                 "Bisshopp & Drucker 1945", "Mattiasson 1981", "Dowell & Traybar 1975",
                 "Featherstone", "Carpentier", "Soft Robotics", "IEEE Transactions on Robotics"):
        assert cite in " ".join(everything.split()), cite


def test_example_files_found_by_name_from_any_directory(tmp_path):
    """From the sources, away from the checkout: every example robot and
    scenario loads by name."""
    code = textwrap.dedent("""
        from soft_twin_core.robot.mechanism import load_mechanism
        from soft_twin_core.robot.model import example_files
        from soft_twin_core.files.scenario import load_scenario
        robots, scenarios = example_files("robots"), example_files("scenarios")
        for name in robots:
            load_mechanism(name)                 # classic and tree robot files alike
        for name in scenarios:
            load_scenario(name)
        print(sorted(robots), sorted(scenarios))
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = _run([sys.executable, "-c", code], timeout=300, cwd=tmp_path, env=env)
    assert "tendon_arm" in proc.stdout and "tendon_arm_dynamics" in proc.stdout


@pytest.mark.slow
def _checkout_caches_are_current():
    """True when the checkout's kernel caches were compiled from its sources (`make setup`'s warm-up)."""
    from soft_twin_core.engine.kernels._caches import kernel_digest
    stamp = CORE / "__pycache__" / "soft_twin_kernels.sha256"
    return stamp.is_file() and stamp.read_text().strip() == kernel_digest(CORE)


FIRST_USE = textwrap.dedent("""
    from soft_twin_core.robot.mechanism import from_robot_model, load_mechanism
    from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
    from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
    solve_equilibrium(load_mechanism("tendon_arm"))
    sim = MechanismSimulator(from_robot_model(model_from_dict(benchmark_cantilever_dict(10, "all"))), 2e-3)
    sim.step(n=500)
    print("first statics and 1 s of dynamics done")
""")


@pytest.mark.skipif(not _checkout_caches_are_current(), reason="the checkout's kernel caches are stale: make setup")
def test_pip_install_core_in_plain_venv(tmp_path):
    """A wheel of the core, built from the warmed-up checkout, in a venv
    without any ROS wheel: soft_twin_core imports, rclpy does not; the
    wheel's kernel caches serve a new process's first statics and 1 s of
    dynamics without compiling (issue 30, shipped caches), in place and
    through NUMBA_CACHE_DIR; every example robot and scenario loads by name
    and the README's Python snippets run, from a directory outside the
    sources."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("setup.py", "pyproject.toml", "README.md", "MANIFEST.in"):
        if (ROOT / name).exists():
            shutil.copy2(ROOT / name, src / name)
    shutil.copytree(CORE, src / "soft_twin_core", ignore=shutil.ignore_patterns("*.pyc"))   # the caches too
    shutil.copytree(ROOT / "config", src / "config")

    base_python = getattr(sys, "_base_executable", None) or sys.executable
    venv = tmp_path / "venv"
    env = _clean_env(PIP_CONSTRAINT=str(CONSTRAINTS), PIP_DISABLE_PIP_VERSION_CHECK="1")
    _run([base_python, "-m", "venv", str(venv)], timeout=120, env=env, cwd=tmp_path)
    py = str(venv / "bin" / "python")
    # PIP_CONSTRAINT pins the runtime deps and the build backend alike;
    # wheels come from pip's cache once `make setup` has run.
    _run([py, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path / "dist"), str(src)], timeout=600,
         env=env, cwd=tmp_path)
    wheel, = (tmp_path / "dist").glob("soft_twin_core-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
    assert "soft_twin_core/__pycache__/soft_twin_kernels.sha256" in names
    assert [n for n in names if n.startswith("soft_twin_core/engine/kernels/__pycache__/") and n.endswith(".nbc")]
    assert not [n for n in names if n.endswith(".pyc")]
    _run([py, "-m", "pip", "install", "-q", str(wheel)], timeout=600, env=env, cwd=tmp_path)

    proc = _run([py, "-c", "import soft_twin_core, sys; print(soft_twin_core.__file__); "
                 "print('rclpy' in sys.modules)"], timeout=120, env=env, cwd=tmp_path)
    where, rclpy_loaded = proc.stdout.split()
    assert Path(where).is_relative_to(venv), where
    assert rclpy_loaded == "False"
    # the wheel's caches serve a new process: numba loads every kernel, saves none (it would after a compile)
    def first_use(**extra):
        p = _run([py, "-c", FIRST_USE], timeout=600, env=dict(env, NUMBA_DEBUG_CACHE="1", **extra), cwd=tmp_path)
        assert "done" in p.stdout and "data loaded" in p.stdout, p.stdout[-3000:]
        saved = [ln for ln in p.stdout.splitlines() if "data saved" in ln]
        assert not saved, saved[:5]
    first_use()
    moved = tmp_path / "numba_cache"                             # an empty cache directory elsewhere:
    first_use(NUMBA_CACHE_DIR=str(moved))                        # the shipped caches are copied there first
    assert len(list(moved.rglob("soft_twin_kernels.sha256"))) >= 2 and list(moved.rglob("*.nbc"))

    proc = subprocess.run([py, "-c", "import rclpy"], capture_output=True, text=True,
                          timeout=120, env=env, cwd=tmp_path)
    assert proc.returncode != 0 and "ModuleNotFoundError" in proc.stderr, proc.stderr
    listed = _run([py, "-m", "pip", "list", "--format=freeze"], timeout=120, env=env).stdout
    assert not [ln for ln in listed.splitlines() if ln.lower().startswith("ros-")], listed
    assert (venv / "bin" / "soft-twin-sim").exists()

    # the example files ship as package data: by name, from anywhere
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.rmtree(src)            # nothing left to find but the install
    robots = sorted(p.stem for p in (ROOT / "config" / "robots").glob("*.yaml"))
    scenarios = sorted(p.stem for p in (ROOT / "config" / "scenarios").glob("*.yaml"))
    code = textwrap.dedent(f"""
        from pathlib import Path
        from soft_twin_core.robot.mechanism import load_mechanism
        from soft_twin_core.robot.model import example_files
        from soft_twin_core.files.scenario import load_scenario
        assert sorted(example_files("robots")) == {robots!r}, example_files("robots")
        assert sorted(example_files("scenarios")) == {scenarios!r}, example_files("scenarios")
        for name in {robots!r}:
            load_mechanism(name)
        for name in {scenarios!r}:
            load_scenario(name)
        print(Path(example_files("robots")["tendon_arm"]))
    """)
    proc = _run([py, "-c", code], timeout=300, env=env, cwd=elsewhere)
    assert Path(proc.stdout.strip()).is_relative_to(venv), proc.stdout
    sim = _run([str(venv / "bin" / "soft-twin-sim"), "statics", "tendon_arm_statics"], timeout=600,
               env=env, cwd=elsewhere)
    assert '"tip_position"' in sim.stdout
    # the README's Python snippets, as a user would paste them
    for i, snippet in enumerate(readme_python_snippets()):
        f = elsewhere / f"readme_{i}.py"
        f.write_text(snippet)
        _run([py, str(f)], timeout=900, env=env, cwd=elsewhere)


# ------------------------------------------------- ROS package (make setup)

INTERFACE_IMPORTS = textwrap.dedent("""
    import sys
    from soft_twin.msg import ActuationCommand, Strains
    from soft_twin.srv import ForwardKinematics, InverseKinematics, StaticsQuery
    from std_srvs.srv import Trigger
    import soft_twin, soft_twin_core
    assert hasattr(ForwardKinematics.Response(), "backbone")
    assert hasattr(StaticsQuery.Response(), "base_wrench")
    assert list(ActuationCommand(names=["t1"], values=[1.0]).values) == [1.0]
    print(soft_twin.msg.__file__)
    print(soft_twin_core.__file__)
""")


def _in_make_venv():
    """True in the .venv that scripts/setup_env.sh built (it leaves a stamp)."""
    return Path(sys.prefix, ".soft_twin-deps.sha256").exists()


@pytest.mark.ros
def test_interfaces_import_from_sources():
    """Tests run with the checkout first on sys.path (pyproject.toml): the source
    soft_twin/ extends its path to the installed generated msg/srv modules."""
    pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    proc = _run([sys.executable, "-c", INTERFACE_IMPORTS], timeout=120, cwd=ROOT)
    msg_file, core_file = map(Path, proc.stdout.split())
    assert not msg_file.is_relative_to(ROOT / "soft_twin"), msg_file
    assert core_file.is_relative_to(ROOT / "soft_twin_core"), core_file


@pytest.mark.ros
def test_interfaces_import_from_install(tmp_path):
    """Away from the checkout only the install is seen: it must be complete."""
    pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
    proc = _run([sys.executable, "-c", INTERFACE_IMPORTS], timeout=120, cwd=tmp_path)
    msg_file, core_file = map(Path, proc.stdout.split())
    assert not msg_file.is_relative_to(ROOT / "soft_twin"), msg_file
    assert not core_file.is_relative_to(ROOT / "soft_twin_core"), core_file
    # the hand-written modules are installed next to the generated ones
    installed = msg_file.parents[1]
    for mod in ROOT.joinpath("soft_twin").glob("*.py"):
        if mod.name != "__init__.py":
            assert (installed / mod.name).exists(), mod.name


@pytest.mark.ros
@pytest.mark.skipif(not _in_make_venv(), reason="checks the .venv of `make setup`")
def test_commands_installed():
    for name, target in (("soft_twin_node", "from soft_twin.node import main"),
                         ("soft-twin-sim", "from soft_twin_core.cli import main")):
        for folder in (Path(sys.prefix, "bin"), Path(sys.prefix, "lib", "soft_twin")):
            exe = folder / name
            assert exe.exists() and os.access(exe, os.X_OK), exe
            text = exe.read_text()
            shebang = text.splitlines()[0]
            assert Path(shebang[2:]).parent == Path(sys.prefix, "bin"), shebang
            assert target in text


@pytest.mark.ros
def test_custom_service_round_trip():
    """The generated type support loads: a ForwardKinematics call within one process."""
    rclpy = pytest.importorskip("rclpy", reason="needs the venv of `make setup`")
    from geometry_msgs.msg import Pose
    from rclpy.executors import SingleThreadedExecutor
    from soft_twin.srv import ForwardKinematics

    def handle(req, resp):
        resp.backbone.poses = [Pose() for _ in range(len(req.strains) // 6 + 1)]
        resp.success, resp.message = True, "ok"
        return resp

    context = rclpy.Context()
    rclpy.init(context=context)
    try:
        server = rclpy.create_node("packaging_fk_server", context=context)
        client_node = rclpy.create_node("packaging_fk_client", context=context)
        server.create_service(ForwardKinematics, "packaging_fk", handle)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(server)
        executor.add_node(client_node)
        client = client_node.create_client(ForwardKinematics, "packaging_fk")
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(ForwardKinematics.Request(strains=[0.0] * 12))
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        resp = future.result()
        assert resp is not None and resp.success and len(resp.backbone.poses) == 3
        executor.shutdown()
        server.destroy_node()
        client_node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def test_ros_domain_id_is_private():
    domain = int(os.environ["ROS_DOMAIN_ID"])
    assert 1 <= domain <= 101
