"""The colcon path of the docs (docs/development.md, "Building with
colcon"), built for real: ``colcon build`` of this checkout (one ROS
package, build type ament_cmake) into an install space, against the ROS
wheels of the venv (their prefix as the underlay, as /opt/ros/jazzy would
be), and the install used as the docs say, its ``setup.sh`` sourced in a
fresh shell: the generated interfaces, the node package and the core import
from the install (not from the checkout), the commands and the config files
are where the docs put them; the build gives the install its kernel
caches (the source tree's, warmed by ``make setup``, copied: the build's
``warmup --install-to`` step), and the node started from the install
reaches its first state with every kernel loaded from them: not one cache
file of the install is written (a compile would write its own)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy", reason="needs ROS 2: the venv of `make setup`")
pytest.importorskip("colcon_core", reason="needs colcon: the venv of `make setup`")

ROOT = Path(__file__).resolve().parents[2]
VENV = Path(sys.prefix)


def _sources(dest):
    """The checkout's sources copied to ``dest`` (a workspace's src/soft_twin,
    as the docs clone it), with its kernel caches (a checkout that ran
    ``make setup``), not its bytecode: the venv inside the checkout must not
    lie under the package's source folder (CMake refuses include paths
    there)."""
    top = {".venv", "build", "install", "log", ".git", ".pytest_cache", ".hypothesis"}

    def ignore(folder, names):
        return [n for n in names if n.endswith(".pyc") or (Path(folder) == ROOT and n in top)]
    shutil.copytree(ROOT, dest, ignore=ignore, symlinks=True)
    return dest


def test_colcon_builds_the_package_and_its_install_space_works(tmp_path):
    src = _sources(tmp_path / "src" / "soft_twin")
    env = dict(os.environ, PATH=f"{VENV / 'bin'}:{os.environ.get('PATH', '')}", CMAKE_PREFIX_PATH=str(VENV),
               AMENT_PREFIX_PATH=str(VENV))
    build = subprocess.run([str(VENV / "bin" / "colcon"), "--log-base", str(tmp_path / "log"), "build",
                            "--paths", str(src), "--build-base", str(tmp_path / "build"),
                            "--install-base", str(tmp_path / "install")],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    assert "Finished <<< soft_twin" in build.stdout + build.stderr
    install = tmp_path / "install"
    prefix = install / "soft_twin"
    for f in ("share/soft_twin/package.xml", "share/soft_twin/config/params.yaml",
              "share/soft_twin/config/robots/tendon_arm.yaml", "lib/soft_twin/soft_twin_node",
              "lib/soft_twin/soft_twin_estimator", "lib/soft_twin/soft-twin-sim"):
        assert (prefix / f).is_file(), f
    assert os.access(prefix / "lib/soft_twin/soft_twin_node", os.X_OK)
    check = ("import soft_twin, soft_twin_core, soft_twin.node, soft_twin.estimator\n"
             "from soft_twin.msg import ActuationCommand\n"
             "from soft_twin.srv import ForwardKinematics\n"
             "print(soft_twin.__file__); print(soft_twin_core.__file__)\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}      # the underlay as the suite has it
    env.update(PATH=f"{VENV / 'bin'}:{env.get('PATH', '')}", AMENT_PREFIX_PATH=str(VENV))
    # a fresh shell, away from the checkout (whose soft_twin/ would shadow the install's)
    run = subprocess.run(["bash", "-c", f". '{install}/setup.sh' && python -c \"$CHECK\" && "
                                        f"'{prefix}/lib/soft_twin/soft-twin-sim' --help"],
                         cwd=tmp_path, env=dict(env, CHECK=check), capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    where = run.stdout.splitlines()[:2]
    assert all(w.startswith(str(prefix)) for w in where), where
    assert "usage" in run.stdout.lower()
    shutil.rmtree(tmp_path / "build", ignore_errors=True)

    core = Path(where[1]).parent
    caches = lambda: {(f.name, f.stat().st_size, f.stat().st_mtime_ns)                # noqa: E731
                      for f in core.rglob("*.nb[ic]")}
    before = caches()
    assert len(before) > 100, (len(before), "the build gave the install no kernel caches")
    from soft_twin.client import TwinClient, interrupt
    name = "colcon_twin"
    log = open(tmp_path / "node.log", "w")
    node = subprocess.Popen(["bash", "-c", f". '{install}/setup.sh' && exec '{prefix}/lib/soft_twin/soft_twin_node' "
                                           f"--ros-args -r __node:={name}"],
                            cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT, text=True)
    client = TwinClient(name, client_name=f"{name}_test_client")
    try:
        client.wait_ready(300.0)
        assert client.backbone is not None and len(client.backbone.poses) > 10
    finally:
        client.close()
        interrupt(node)
        log.close()
    out = (tmp_path / "node.log").read_text()
    assert node.returncode == 0 and "Traceback" not in out, out[-3000:]
    assert caches() == before, "the node compiled kernels instead of loading the copied caches"
