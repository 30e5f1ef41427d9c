"""Start-up of a new process (issue 10): numba's BLAS probe is answered
without importing scipy.linalg, and a kernel that does use BLAS still works.

Each check runs in a fresh interpreter (the probe happens once per process,
at numba's first compile or cache load).
"""

import os
import subprocess
import sys
import textwrap
import time

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _run(code):
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env, capture_output=True, text=True,
                       timeout=300, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    return p.stdout


def test_statics_and_dynamics_start_without_scipy_linalg():
    out = _run("""
        import sys
        from soft_twin_core.solve.constrained import MechanismSimulator, solve_equilibrium
        from soft_twin_core.robot.mechanism import from_robot_model
        from soft_twin_core.robot.model import benchmark_cantilever_dict, model_from_dict
        m = from_robot_model(model_from_dict(benchmark_cantilever_dict(2, "all")))
        solve_equilibrium(m)
        MechanismSimulator(m, 2e-3).step(n=5)
        import numba.np.arraymath as am, numba.np.linalg as nl
        print(am._HAVE_BLAS, "scipy.linalg" in sys.modules, am.ensure_blas is nl.ensure_blas,
              nl.ensure_blas.__module__)
    """)
    assert out.split() == ["True", "False", "True", "numba.np.linalg"]


def test_a_blas_kernel_still_compiles_after_the_skipped_probe():
    # np.dot of two vectors goes through BLAS when numba found one (the
    # probe's answer); np.linalg.solve through LAPACK: both import scipy.linalg
    # at compile time, with the real probe
    out = _run("""
        import sys
        import numba as nb, numpy as np
        import soft_twin_core.engine.kernels  # noqa: F401  (skips the probe)
        assert "scipy.linalg" not in sys.modules

        @nb.njit
        def f(a, b, A):
            return np.dot(a, b), np.linalg.solve(A, b)

        a, b = np.array([1.0, 2.0, 3.0]), np.array([4.0, -5.0, 6.0])
        A = np.array([[4.0, 1.0, 0.0], [1.0, 3.0, 1.0], [0.0, 1.0, 2.0]])
        d, x = f(a, b, A)
        assert d == 12.0 and np.allclose(A @ x, b, rtol=0, atol=1e-14)
        print("scipy.linalg" in sys.modules)
    """)
    assert out.split() == ["True"]


def test_probe_is_left_alone_once_numba_has_run():
    out = _run("""
        import numba.np.arraymath  # noqa: F401  (numba's own probe, with scipy.linalg)
        from soft_twin_core.engine.kernels._blas_probe import skip_probe
        print(skip_probe())
    """)
    assert out.split() == ["False"]


def test_warm_up_purges_every_kernel_cache_when_a_source_changes(tmp_path):
    """numba checks a cached kernel against its own file only, so a change in
    a file a kernel's file imports (a callee, a constant) must clear the
    package's caches (warmup.purge_stale_caches); a change in a file no
    kernel depends on keeps them (issue 30: compile less)."""
    from soft_twin_core.engine.kernels._caches import kernel_sources
    from soft_twin_core.warmup import purge_stale_caches
    pkg = tmp_path / "soft_twin_core"
    (pkg / "kernels" / "__pycache__").mkdir(parents=True)
    (pkg / "a.py").write_text("from soft_twin_core.c import z\nx = 1\n")
    (pkg / "c.py").write_text("z = 0\n")
    (pkg / "views.py").write_text("def draw():\n    from soft_twin_core import a\n")
    (pkg / "kernels" / "b.py").write_text("from numba import njit\nfrom soft_twin_core.a import x\n")
    assert kernel_sources(pkg) == sorted([pkg / "a.py", pkg / "c.py", pkg / "kernels" / "b.py"])
    caches = [pkg / "kernels" / "__pycache__" / "b.f-1.py311.nbi", pkg / "kernels" / "__pycache__" / "b.f-1.py311.1.nbc"]
    assert purge_stale_caches(pkg)                     # first time: no stamp
    for c in caches:
        c.write_bytes(b"cache")
    assert not purge_stale_caches(pkg)                 # nothing changed: caches kept
    (pkg / "views.py").write_text("def draw():\n    pass\n")   # no kernel imports it: caches kept
    assert not purge_stale_caches(pkg)
    assert all(c.exists() for c in caches)
    for f, text in (("a.py", "from soft_twin_core.c import z\nx = 3\n"), ("c.py", "z = 1\n")):
        for c in caches:                               # a kernel's import changes, directly or not
            c.write_bytes(b"cache")
        (pkg / f).write_text(text)
        assert purge_stale_caches(pkg), f
        assert not any(c.exists() for c in caches)
        assert not purge_stale_caches(pkg)


def _two_copies(tmp_path):
    """Two copies ("checkout", "venv") of a tiny package: a kernel in
    kernels/b.py reading a constant of a.py."""
    copies = []
    for name in ("checkout", "venv"):
        pkg = tmp_path / name / "soft_twin_core"
        (pkg / "kernels").mkdir(parents=True)
        (pkg / "__init__.py").write_text("")
        (pkg / "kernels" / "__init__.py").write_text("")
        (pkg / "a.py").write_text("x = 1\n")
        (pkg / "kernels" / "b.py").write_text("import numba\nfrom soft_twin_core.a import x\n"
                                              "@numba.njit(cache=True)\ndef f(y):\n    return y + x\n")
        copies.append(pkg)
    return copies


def test_warm_up_purge_reaches_numba_cache_dir_but_not_another_copy(tmp_path, monkeypatch):
    """With NUMBA_CACHE_DIR, numba keeps each source directory's caches in
    <dir>_<sha1 of its path>: the purge clears this copy's there and leaves
    another copy's (the venv's, warmed up at the same time by make setup)."""
    from numba.core.caching import _CacheLocator
    from soft_twin_core.warmup import purge_stale_caches
    cache = tmp_path / "numba_cache"
    copies = _two_copies(tmp_path)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    for pkg in copies:
        assert purge_stale_caches(pkg)                 # first time: no stamp
    # numba's own cache files for each copy's kernel, in a subprocess with that cache dir
    for pkg in copies:
        subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); "
                        "from soft_twin_core.kernels.b import f; f(1)", str(pkg.parent)],
                       check=True, env=dict(os.environ, NUMBA_CACHE_DIR=str(cache)))
    where = {pkg: cache / _CacheLocator.get_suitable_cache_subpath(str(pkg / "kernels" / "b.py")) for pkg in copies}
    assert all(list(d.glob("*.nbi")) and list(d.glob("*.nbc")) for d in where.values()), list(cache.rglob("*"))
    checkout, venv = copies
    (checkout / "a.py").write_text("x = 2\n")         # the checkout changes
    assert purge_stale_caches(checkout)
    assert not list(where[checkout].glob("*.nb*"))
    assert list(where[venv].glob("*.nbi")) and list(where[venv].glob("*.nbc"))


def test_an_installed_copy_takes_the_checkouts_kernel_caches(tmp_path, monkeypatch):
    """Issue 30, compile once: the copy of the package installed in a venv
    takes the warmed-up checkout's caches (warmup.copy_caches) and loads its
    kernels from them instead of compiling (numba says "data loaded" under
    NUMBA_DEBUG_CACHE, where it would say "data saved"); a copy whose
    kernels' sources differ gets none."""
    from soft_twin_core.warmup import copy_caches, purge_stale_caches
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    copies = _two_copies(tmp_path)
    checkout, venv = copies
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}

    def call(pkg):
        out = subprocess.run([sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); "
                              "from soft_twin_core.kernels.b import f; print(f(1))", str(pkg.parent)],
                             check=True, capture_output=True, text=True, env=dict(env, NUMBA_DEBUG_CACHE="1"))
        return out.stdout
    assert purge_stale_caches(checkout)
    assert "data saved" in call(checkout)                        # compiled, cached
    assert copy_caches(checkout, venv) == 2                      # its index and its data
    assert not purge_stale_caches(venv)                          # the stamp came along: nothing purged
    got = call(venv)
    assert "data loaded" in got and "data saved" not in got and got.split()[-1] == "2"
    (venv / "a.py").write_text("x = 2\n")                        # the sources differ: nothing copied
    assert copy_caches(checkout, venv) is None


def test_the_warm_up_compiles_its_parts_side_by_side(monkeypatch, capsys, tmp_path):
    """Issue 30, compile in parallel: the lanes after the first go to
    processes of their own (as many as the cores), the rest run here
    meanwhile; a lane whose process fails is named with its output (and
    left to the final run). A part that needs another one compiled
    elsewhere waits for its mark, and leaves its own even when it fails."""
    import os as _os
    from soft_twin_core import warmup
    ran = []
    monkeypatch.setattr(warmup, "run", lambda parts, marks=None: ran.append((parts, marks is not None)))
    monkeypatch.setattr(_os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    lanes = (("rods",), ("no_such_part",), ("leaves",), ("contact",))     # (leaves: needs no other part)
    assert warmup.compile_side_by_side(lanes) == 2
    assert ran == [(("rods", "contact"), True)]                     # the first lane and those beyond the cores
    err = capsys.readouterr().err
    assert "warm-up of parts no_such_part failed (exit 2)" in err and "usage" in err
    assert "parts leaves failed" not in err and "part leaves:" in err
    monkeypatch.setattr(_os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert warmup.compile_side_by_side(lanes) == 0 and ran[-1] == (("rods", "no_such_part", "leaves", "contact"),
                                                                     False)
    # the marks: a part waits for the one it needs; a failure marks the lane's parts done
    monkeypatch.undo()
    done = []
    monkeypatch.setattr(warmup, "tiny_pass_runs", lambda: done.append("passes"))
    monkeypatch.setattr(warmup, "tiny_contact_run", lambda: done.append("contact") or 1 / 0)
    monkeypatch.setattr(warmup, "WAIT_S", 30.0)
    (tmp_path / "passes").touch()
    with pytest.raises(ZeroDivisionError):
        warmup.run(("contact", "ik"), tmp_path)
    assert done == ["contact"] and (tmp_path / "contact").exists()
    assert (tmp_path / "ik").exists()             # never run, marked: a lane waiting for it goes on
    (tmp_path / "passes").unlink()
    monkeypatch.setattr(warmup, "WAIT_S", 0.3)
    t0 = time.perf_counter()
    with pytest.raises(ZeroDivisionError):
        warmup.run(("contact",), tmp_path)            # no mark: it waits WAIT_S, then compiles what it needs
    assert time.perf_counter() - t0 >= 0.3
    warmup.run(("passes",), tmp_path)
    assert (tmp_path / "passes").exists()

# ---------------------------------------------- kernel caches that travel (issue 30, shipped caches)

_TARGET = """
    import os, sys
    {before}
    import soft_twin_core.engine.kernels  # noqa: F401  (chooses the target)
    from numba.core.registry import cpu_target
    print(cpu_target.target_context.codegen().magic_tuple()[1], os.environ.get("NUMBA_CPU_NAME"))
"""


def _target(before="", **env):
    base = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES",
                                                            "SOFT_TWIN_KERNEL_CPU")}
    code = textwrap.dedent(_TARGET).format(before=before)
    p = subprocess.run([sys.executable, "-c", code], env=dict(base, PYTHONPATH=ROOT, **env), capture_output=True,
                       text=True, timeout=300, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    return p.stdout.split()


def test_the_kernels_compile_for_the_x86_64_v3_baseline_unless_told_otherwise():
    """The target numba compiles the kernels for: x86-64-v3 on a host that
    has its features (and its children inherit it), else the host's; the
    user's NUMBA_CPU_NAME, SOFT_TWIN_KERNEL_CPU=host, and a numba that has
    already compiled (its target machine is fixed) are left alone."""
    import llvmlite.binding as ll
    from soft_twin_core.engine.kernels._caches import KERNEL_CPU, V3_FEATURES
    host = ll.get_host_cpu_name()
    has_v3 = ll.get_process_triple().startswith("x86_64") and V3_FEATURES <= {
        k for k, on in ll.get_host_cpu_features().items() if on}
    assert _target() == ([KERNEL_CPU, KERNEL_CPU] if has_v3 else [host, "None"])
    assert _target(SOFT_TWIN_KERNEL_CPU="host") == [host, "None"]
    with pytest.warns(RuntimeWarning, match="SOFT_TWIN_KERNEL_CPU='native' is not understood"):
        from soft_twin_core.engine.kernels._caches import choose_cpu_target
        choose_cpu_target({"SOFT_TWIN_KERNEL_CPU": "native", "NUMBA_CPU_NAME": "x"})   # (numba left alone)
    assert _target(NUMBA_CPU_NAME="generic") == ["generic", "generic"]
    before = "import numba\nnumba.njit(lambda x: x + 1)(1)"
    assert _target(before) == [host, "None"]


def test_shipped_caches_are_mirrored_once_and_again_after_an_upgrade(tmp_path):
    """mirror_shipped: the shipped files are copied where numba caches, with
    a stamp; a second call copies nothing, and a kernel compiled there later
    stays; another digest (an upgrade) removes every old cache first."""
    from soft_twin_core.engine.kernels._caches import STAMP, mirror_shipped
    src, dst = tmp_path / "shipped", tmp_path / "cache"
    src.mkdir()
    for name in ("m.f-10.py311.nbi", "m.f-10.py311.0.nbc", "m.cpython-311.pyc"):
        (src / name).write_bytes(name.encode())
    dst.mkdir()
    (dst / "old.g-3.py311.nbi").write_bytes(b"another version's")
    assert mirror_shipped(src, dst, "d1") == 2
    assert sorted(p.name for p in dst.iterdir()) == ["m.f-10.py311.0.nbc", "m.f-10.py311.nbi", STAMP]
    assert (dst / "m.f-10.py311.0.nbc").read_bytes() == b"m.f-10.py311.0.nbc"
    (dst / "m.h-20.py311.nbi").write_bytes(b"compiled here")
    assert mirror_shipped(src, dst, "d1") == 0 and (dst / "m.h-20.py311.nbi").exists()
    assert mirror_shipped(src, dst, "d2") == 2 and not (dst / "m.h-20.py311.nbi").exists()
    assert (dst / STAMP).read_text().strip() == "d2"
    for f in dst.glob("*.nb?"):                        # a purge emptied it: copied again
        f.unlink()
    assert mirror_shipped(src, dst, "d2") == 2
