"""Kernel caches that travel: one CPU target for every x86-64 machine that
has it, and the caches a wheel or an install space ships.

numba keys a cached kernel by the CPU it was compiled for, its name and
feature list (``codegen.magic_tuple()``), and by its source file's content
hash. Compiled for the host CPU (numba's default), a cache serves that model
of CPU only. Compiled for a fixed baseline, it serves every machine with
that baseline, so ``make setup`` on one machine, a wheel built there and a
user's machine share one cache:

* :func:`choose_cpu_target` makes numba compile for ``x86-64-v3`` (AVX2,
  FMA, BMI2: every x86-64 CPU since 2013-2015) when the host has those
  features, before the first kernel compiles or loads. It costs at most
  a few per cent against the host's own model on this project's machine
  (an AVX-512 CPU; ``benchmarks/bench_cpu_target.py``, docs/performance.md),
  where the generic x86-64 target (SSE2, no FMA) costs more. It leaves
  numba alone when the user chose (``NUMBA_CPU_NAME``), when
  ``SOFT_TWIN_KERNEL_CPU=host`` says so, on other CPUs, and when numba
  has already compiled something in this process (its target machine is
  fixed from then on).
* :class:`ShippedCaches` serves the caches shipped inside the installed
  package (its ``__pycache__`` directories, put there by the wheel or by
  ``warmup --copy-to``) when numba will not use them in place: the package
  directory is read-only (a system install; numba then caches in the
  user's cache directory) or ``NUMBA_CACHE_DIR`` moves the caches. It
  copies them there once, and again when the shipped set changes (an
  upgrade; the kernels' source digest that ``warmup`` stamps says so).

numba falls back on compiling whatever no cache serves, so neither changes
a result: the target changes the order of floating-point sums only (the
kernels' fastmath contract/reassoc), which every test tolerates.
"""

import os
import shutil
from pathlib import Path

#: the CPU the kernels are compiled for when the host has its features
KERNEL_CPU = "x86-64-v3"
#: x86-64-v3's features, LLVM's names (v2's and v1's included)
V3_FEATURES = frozenset({"cmov", "cx8", "fxsr", "mmx", "sse", "sse2", "cx16", "popcnt", "sahf", "sse3", "sse4.1",
                         "sse4.2", "ssse3", "avx", "avx2", "bmi", "bmi2", "f16c", "fma", "lzcnt", "movbe", "xsave"})
#: the package's root: the caches under it are the shipped ones
PACKAGE = Path(__file__).resolve().parents[2]
#: beside the shipped caches: the digest of the kernels' sources they were compiled from (soft_twin_core.warmup)
STAMP = "soft_twin_kernels.sha256"


def choose_cpu_target(environ=os.environ):
    """Compile for :data:`KERNEL_CPU` (see the module); returns the CPU
    name numba compiles for from now on, or None when it was left alone."""
    choice = environ.get("SOFT_TWIN_KERNEL_CPU", "")
    if choice.strip().lower() not in ("", "host"):
        import warnings
        warnings.warn(f"SOFT_TWIN_KERNEL_CPU={choice!r} is not understood (only 'host', or unset): "
                      f"the kernels compile for {KERNEL_CPU} where the CPU has it", RuntimeWarning, stacklevel=2)
    if environ.get("NUMBA_CPU_NAME") or choice.strip().lower() == "host":
        return None
    from numba.core import config
    from numba.core.registry import cpu_target
    if "_toplevel_target_context" in vars(cpu_target):     # numba's target machine exists: too late
        return None
    import llvmlite.binding as ll
    if not ll.get_process_triple().startswith("x86_64"):
        return None
    host = {name for name, on in ll.get_host_cpu_features().items() if on}
    if not V3_FEATURES <= host:
        return None
    # In the environment, not only numba's config: numba re-reads the environment before every compile,
    # and the warm-up's side processes and Dask's workers inherit it.
    environ["NUMBA_CPU_NAME"], environ["NUMBA_CPU_FEATURES"] = KERNEL_CPU, ""
    config.reload_config()
    return KERNEL_CPU


def _shipped_digest():
    f = PACKAGE / "__pycache__" / STAMP
    return f.read_text().strip() if f.is_file() else None


_MIRRORED = set()          # the cache directories this process has brought up to date


def mirror_shipped(src_dir, dst_dir, digest):
    """Make ``dst_dir`` hold the caches of ``src_dir`` (a shipped
    ``__pycache__``) unless it already holds the ones of this ``digest``:
    its old kernel caches are removed first (they may be another version's,
    whose callees in other files changed), then a stamp is written. Kernels
    compiled there later stay until the shipped set changes (or a purge
    empties the directory). Returns the number of files copied."""
    dst_dir = Path(dst_dir)
    stamp = dst_dir / STAMP
    if stamp.is_file() and stamp.read_text().strip() == digest and any(dst_dir.glob("*.nbi")):
        return 0
    dst_dir.mkdir(parents=True, exist_ok=True)
    for old in list(dst_dir.glob("*.nbi")) + list(dst_dir.glob("*.nbc")):
        old.unlink(missing_ok=True)
    n = 0
    for f in sorted(Path(src_dir).iterdir()):
        if f.suffix in (".nbi", ".nbc"):
            tmp = dst_dir / (f.name + f".{os.getpid()}.tmp")
            shutil.copyfile(f, tmp)
            os.replace(tmp, dst_dir / f.name)          # another process loading meanwhile sees whole files
            n += 1
    stamp.write_text(digest + "\n")
    return n


def _make_locator_class():
    from numba.core import caching

    class ShippedCaches(caching._CacheLocator):
        """numba's choice of cache directory for a kernel of this package
        (the user's ``NUMBA_CACHE_DIR``, the package's own ``__pycache__``,
        else the user's cache directory), with the shipped caches copied
        into it when it is not the ``__pycache__`` they ship in."""

        @classmethod
        def from_function(cls, py_func, py_file):
            src = Path(py_file).resolve().parent / "__pycache__"
            if PACKAGE not in src.parents:
                return None                            # not this package's: numba's own choice
            for other in caching.CacheImpl._locator_classes:
                if other is cls:
                    continue
                locator = other.from_function(py_func, py_file)
                if locator is not None:
                    break
            else:
                return None
            dst = Path(locator.get_cache_path()).resolve()
            if dst == src or dst in _MIRRORED:         # in place (the common case), or done already
                return locator
            _MIRRORED.add(dst)
            digest = _shipped_digest()
            if digest and src.is_dir():
                try:
                    mirror_shipped(src, dst, digest)
                except OSError:
                    pass                               # numba compiles what it cannot load
            return locator

    return ShippedCaches


def install_locator():
    """Put :class:`ShippedCaches` first in numba's locators (it declines any
    file outside this package: numba's own choice there); idempotent.
    Returns the class."""
    from numba.core import caching
    for cls in caching.CacheImpl._locator_classes:
        if cls.__name__ == "ShippedCaches":
            return cls
    cls = _make_locator_class()
    caching.CacheImpl._locator_classes.insert(0, cls)
    return cls


# ----------------------------------------------- which sources a cache depends on

#: files under the package's root that hold no kernel and nothing a kernel reads
NOT_KERNELS = ("warmup.py", "engine/kernels/_caches.py")

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
    count. :data:`NOT_KERNELS` are not kernels, nor read by one: the
    warm-up driver, and this module (the CPU target it chooses is part of
    numba's own cache key)."""
    import ast
    root = Path(root)

    def is_kernel_file(f):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "numba" for a in node.names):
                return True
            if isinstance(node, ast.ImportFrom) and node.module and (
                    node.module.split(".")[0] == "numba" or any(a.name.startswith("_jit") for a in node.names)):
                return True
        return False
    skip = {root / f for f in NOT_KERNELS}
    todo = [f for f in sorted(root.rglob("*.py")) if f not in skip and is_kernel_file(f)]
    seen = set(todo)
    while todo:
        for g in _top_level_imports(todo.pop(), root):
            if g not in seen and g not in skip:
                seen.add(g)
                todo.append(g)
    return sorted(seen)


def kernel_digest(root):
    """The hash of the kernels' sources under ``root`` (paths and contents)."""
    import hashlib
    h = hashlib.sha256()
    for f in kernel_sources(root):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()
