"""Every script of examples/ runs as a user runs it (a fresh interpreter,
another working directory) and prints its results; the README's Python
blocks are run by test/integration/test_packaging.py."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = sorted((ROOT / "examples").glob("*.py"))


def test_there_are_examples():
    assert len(EXAMPLES) >= 3


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs(script, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = [ln for ln in r.stdout.splitlines() if ln.strip()]
    assert len(lines) >= 2 and "nan" not in r.stdout.lower(), r.stdout


def _python_blocks(page):
    text = page.read_text(encoding="utf-8")
    return [b.split("```", 1)[0] for b in text.split("```python\n")[1:]]


def doc_imports():
    """Every ``from soft_twin_core... import ...`` of a Python block of the
    README and the docs pages, as (page, statement)."""
    import ast
    out = []
    for page in [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md")):
        for block in _python_blocks(page):
            for line in block.splitlines():
                if line.startswith(("from soft_twin_core", "import soft_twin_core")):
                    node = ast.parse(line).body[0]
                    out.append((page.name, ast.unparse(node)))
    return out


def test_every_import_the_docs_show_resolves():
    """The pages' code names modules and names that exist (a module moved
    into a folder, a name renamed: the page would break a user's paste)."""
    found = doc_imports()
    assert len(found) >= 10 and any(p == "README.md" for p, _ in found)
    for page, stmt in found:
        try:
            exec(stmt, {})
        except ImportError as e:
            raise AssertionError(f"{page}: {stmt}: {e}") from None
    with pytest.raises(ImportError):            # the check can fail
        exec("from soft_twin_core.model import load_model", {})


def test_the_public_names_come_from_their_modules_and_load_lazily():
    import importlib

    import soft_twin_core
    for name, module in soft_twin_core.PUBLIC.items():
        obj = getattr(soft_twin_core, name)
        assert obj is getattr(importlib.import_module(module), name)
        assert obj.__module__ == module, (name, obj.__module__)      # defined there, not re-exported
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        soft_twin_core.nope
    code = "import sys, soft_twin_core, soft_twin_core.lie; print('numba' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.stdout.strip() == "False", r.stdout + r.stderr
