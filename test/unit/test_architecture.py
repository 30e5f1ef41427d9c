"""The code's shape, checked: no import circle (imports inside functions
included), every exception type in ``errors``, every joint kind defined
once. A short ``ast`` walk of the sources; no module is imported."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("soft_twin_core", "soft_twin")


def _modules():
    out = {}
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            out[name[:-len(".__init__")] if name.endswith(".__init__") else name] = f
    return out


def _imported(name, path, node, known):
    """The package modules an Import/ImportFrom node names."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name in known}
    base = node.module or ""
    if node.level:
        parts = name.split(".")
        keep = len(parts) - node.level + (1 if path.name == "__init__.py" else 0)
        base = ".".join(parts[:keep] + ([node.module] if node.module else []))
    cands = {base} | {f"{base}.{a.name}" for a in node.names}
    return {c for c in cands if c in known and c != name}


def import_graph():
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        graph[name] = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                graph[name] |= _imported(name, path, node, mods)
    return graph


def cycles(graph):
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_circle_even_through_imports_inside_functions():
    graph = import_graph()
    assert len(graph) > 50 and graph["soft_twin_core.solve.constrained"]          # the walk sees the code
    assert cycles(graph) == []


def test_the_core_imports_nothing_of_ros_or_the_node():
    for name, path in _modules().items():
        if not name.startswith("soft_twin_core"):
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                roots = [a.name.split(".")[0] for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                roots = [(node.module or "").split(".")[0]]
            else:
                continue
            assert not {"rclpy", "soft_twin", "rosbag2_py"} & set(roots), (name, ast.unparse(node))


def test_every_exception_type_of_the_core_is_defined_in_errors():
    """Public ones: a module's private control-flow exception stays with it."""
    where = {}
    for name, path in _modules().items():
        if not name.startswith("soft_twin_core"):
            continue
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.ClassDef) and not node.name.startswith("_") and any(
                    isinstance(b, ast.Name) and (b.id.endswith(("Error", "Exception")) or b.id in ("ValueError",
                                                 "RuntimeError")) for b in node.bases):
                where[node.name] = name
    assert where and all(m == "soft_twin_core.errors" for m in where.values()), where


def test_joint_kinds_are_defined_once():
    kinds = {"FIXED", "REVOLUTE", "PRISMATIC", "SPHERICAL", "FREE", "SOFT"}
    owners = set()
    for name, path in _modules().items():
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Assign):
                names = {t.id for tg in node.targets for t in ast.walk(tg) if isinstance(t, ast.Name)}
                if names & kinds and isinstance(node.value, (ast.Constant, ast.Tuple, ast.Call)):
                    owners.add(name)
    assert owners == {"soft_twin_core.engine.joint_kinds"}, owners


# The floors of the core, lowest first: a module imports only from floors
# below its own (the ground floor's modules are independent of each other's
# floor number but sit at 0). soft_twin (the node) may import any of them
# except the references.
FLOORS = {
    "ground": 0, "engine": 1, "robot": 2, "solve": 3, "planning": 4, "files": 4, "estimation": 5, "viz": 5,
    "reference": 5, "warmup": 6, "twin": 6, "commands": 6, "studies": 7, "cli": 8,
}
GROUND = {"errors", "lie", "_series", "_blas", "limits", "text"}


def _floor(module):
    parts = module.split(".")
    if parts[0] != "soft_twin_core" or len(parts) == 1 or parts[1] in GROUND:
        return "ground" if parts[0] == "soft_twin_core" else None
    return parts[1]


def test_every_core_module_sits_on_a_named_floor():
    floors = {_floor(m) for m in import_graph() if m.startswith("soft_twin_core")}
    assert floors <= set(FLOORS), floors - set(FLOORS)
    assert {"engine", "robot", "solve", "reference", "twin"} <= floors        # the walk sees the folders


def upward_imports(graph):
    """The (importer, imported) pairs across floors that do not point down."""
    return sorted((a, b) for a, deps in graph.items() for b in deps
                  if _floor(a) and _floor(b) and _floor(a) != _floor(b) and FLOORS[_floor(b)] >= FLOORS[_floor(a)])


def test_the_floor_check_finds_an_upward_import():
    graph = {"soft_twin_core.engine.forces": {"soft_twin_core.solve.constrained", "soft_twin_core.lie"},
             "soft_twin_core.files.runs": {"soft_twin_core.planning.planner"},
             "soft_twin_core.solve.constrained": {"soft_twin_core.engine.forces"}}
    assert upward_imports(graph) == [("soft_twin_core.engine.forces", "soft_twin_core.solve.constrained"),
                                     ("soft_twin_core.files.runs", "soft_twin_core.planning.planner")]


def test_each_floor_imports_only_the_floors_below():
    assert upward_imports(import_graph()) == []


def test_no_production_module_imports_the_references():
    graph = import_graph()
    users = sorted(a for a, deps in graph.items() if not a.startswith("soft_twin_core.reference")
                   for b in deps if b.startswith("soft_twin_core.reference"))
    assert users == []


# Core modules that import inside functions on purpose, and why.
LAZY_ON_PURPOSE = {
    "soft_twin_core.cli": "start-up: each subcommand imports only what it runs (--help in milliseconds)",
    "soft_twin_core.warmup": "it purges stale kernel caches before it imports the kernels",
}


def late_imports():
    """(module, line) of every import of the package's own modules inside a
    function of the core, without a '# here:' reason on its line."""
    out = []
    for name, path in _modules().items():
        if not name.startswith("soft_twin_core") or name in LAZY_ON_PURPOSE:
            continue
        lines = path.read_text(encoding="utf-8").splitlines()
        for fn in ast.walk(ast.parse("\n".join(lines))):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(fn):
                own = (isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith(
                    "soft_twin")) or isinstance(node, ast.Import) and node.names[0].name.startswith("soft_twin"))
                if own and "# here:" not in lines[node.lineno - 1]:
                    out.append((name, node.lineno))
    return sorted(set(out))


def test_an_import_inside_a_function_states_its_reason():
    """The floors leave no import circle to break by importing late: the
    core imports its own modules at the top, but where a module says why
    (LAZY_ON_PURPOSE, or a '# here:' comment on the line)."""
    assert late_imports() == []
    assert all(LAZY_ON_PURPOSE.values())
