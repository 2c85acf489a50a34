"""The package's import layering (docs/architecture.md §1): a module imports only from its own layer
or the layers below it, every import counted (function-local ones too), and no two modules import
each other, directly or round a longer cycle."""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "d2gs_np"
# Lowest first; the first part of a module's path under d2gs_np/ names its layer.
LAYERS = (
    ("constants",),
    ("base",),
    ("geometry",),
    ("render",),
    ("pose",),
    ("scene",),
    ("data",),
    ("blur",),
    ("losses",),
    ("optim",),
    ("reference",),
    ("video",),
    ("importers",),
    ("train",),
    ("evaluation",),
    ("reporting",),
    ("experiments",),
    ("refcheck",),
    ("cli", "__main__", "__init__"),
)
RANK = {part: i for i, layer in enumerate(LAYERS) for part in layer}


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__" and len(parts) > 2:
        parts = parts[:-1]
    return ".".join(parts)


def imports_of(path: Path, package_modules) -> set:
    """The d2gs_np modules ``path`` imports (``from d2gs_np.x import y`` counts d2gs_np.x.y when that
    is a module, else d2gs_np.x)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("d2gs_np"))
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("d2gs_np"):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                out.add(sub if sub in package_modules else node.module)
    return out


def layer_of(module: str) -> int:
    parts = module.split(".")
    key = parts[1] if len(parts) > 1 else "__init__"
    if key not in RANK:
        raise AssertionError(f"{module} is in no layer of LAYERS; add it (and to docs/architecture.md §1)")
    return RANK[key]


def import_graph(package=PACKAGE) -> dict:
    files = sorted(package.rglob("*.py"))
    names = {module_name(f) for f in files}
    return {module_name(f): imports_of(f, names) - {module_name(f)} for f in files}


def upward_imports(graph) -> list:
    return sorted(f"{m} (layer {LAYERS[layer_of(m)][0]}) imports {d} (layer {LAYERS[layer_of(d)][0]})"
                  for m, deps in graph.items() for d in deps if d.startswith("d2gs_np.") and layer_of(d) > layer_of(m))


def cycles(graph) -> list:
    """Each import cycle once, as a list of modules (Tarjan's strongly connected components)."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
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
                found.append(sorted(comp))

    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))
    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_no_module_imports_a_higher_layer():
    assert upward_imports(import_graph()) == []


def test_no_import_cycles():
    # package __init__ files re-export their modules; a module importing its own package's
    # __init__ is not a cycle of concepts, so the __init__ files are left out here
    graph = {m: {d for d in deps if not _is_package(d)} for m, deps in import_graph().items() if not _is_package(m)}
    assert cycles(graph) == []


def _is_package(module):
    return (PACKAGE.parent / Path(*module.split(".")) / "__init__.py").exists()


def test_the_checks_catch_a_planted_upward_import_and_cycle(tmp_path):
    # a copy of the package with render/ importing train/, and two train modules importing each other
    import shutil
    pkg = tmp_path / "d2gs_np"
    shutil.copytree(PACKAGE, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    api = pkg / "render" / "api.py"
    api.write_text(api.read_text() + "\n\ndef _planted():\n    from d2gs_np.train import trainer  # noqa\n")
    log = pkg / "train" / "log.py"
    log.write_text(log.read_text() + "\n\ndef _planted():\n    from d2gs_np.train import trainer  # noqa\n")
    graph = {module_name_in(pkg, f): imports_of(f, {module_name_in(pkg, g) for g in pkg.rglob("*.py")})
             for f in pkg.rglob("*.py")}
    ups = upward_imports(graph)
    assert any(u.startswith("d2gs_np.render.api (layer render) imports d2gs_np.train.trainer") for u in ups), ups
    assert any("d2gs_np.train.log" in c and "d2gs_np.train.trainer" in c for c in cycles(graph))


def module_name_in(pkg: Path, path: Path) -> str:
    rel = path.relative_to(pkg.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__" and len(parts) > 2:
        parts = parts[:-1]
    return ".".join(parts)


@pytest.mark.parametrize("module", ["d2gs_np.render.config", "d2gs_np.scene.config", "d2gs_np.train.config"])
def test_loading_a_config_imports_no_solver(module):
    # a config is plain data: reading one must not pull in CasADi, OpenCV or the Numba kernels
    code = (f"import sys; import {module}; heavy = sorted(m for m in ('casadi', 'cv2', 'numba') if m in sys.modules); "
            "print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=PACKAGE.parent)
    assert out.stdout.strip() == "", f"importing {module} imports {out.stdout.strip()}"
