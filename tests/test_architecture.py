"""The package's layering (docs/architecture.md), enforced on the source: every import of an
affinebody module (top-level or inside a function) goes down or sideways in

    core <- kinematics <- models <- mechanics <- application <- cli

``quantum``'s solvers use only core and kinematics; the library part (core .. mechanics and the
quantum solvers) never imports the tooling packages; no module imports a private name of
another, and the import graph has no cycle.
"""

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "affinebody"

#: Layer of each module (a package prefix covers its submodules; the longest prefix wins).
LAYERS = {
    "core": ("_checks", "_linalg", "_host", "_host_kernels", "_pair_triton", "_xla", "_pytree",
             "state", "space", "expressions"),
    "kinematics": ("groups", "polar", "deformation", "mutual", "velocities", "momenta",
                   "inertia", "actions", "brackets", "observables"),
    "models": ("kinetic", "potentials", "pair_kernels", "neighbors"),
    "mechanics": ("constraints", "nonholonomic", "system", "integrators", "simulate", "phonons",
                  "pressure", "barostat", "thermostats"),
    "quantum": ("quantum",),
    "application": ("_json", "_timing", "config", "runner", "sweep", "studies", "h5md",
                    "checkpoint", "plotting", "export", "examples", "units", "quantum.config",
                    "quantum.density_files"),
    "cli": ("cli", "quantum.cli", "demo_kinematics"),
}
#: What each layer may import (besides itself).
ALLOWED = {
    "core": set(),
    "kinematics": {"core"},
    "models": {"core", "kinematics"},
    "mechanics": {"core", "kinematics", "models"},
    "quantum": {"core", "kinematics"},
    "application": {"core", "kinematics", "models", "mechanics", "quantum"},
    "cli": {"core", "kinematics", "models", "mechanics", "quantum", "application"},
}
LIBRARY = ("core", "kinematics", "models", "mechanics", "quantum")
TOOLING = {"click", "rich", "pydantic", "h5py", "dask", "distributed", "matplotlib"}


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def layer_of(module: str) -> str | None:
    inner = module.removeprefix("affinebody").removeprefix(".")
    best, found = -1, None
    for layer, prefixes in LAYERS.items():
        for prefix in prefixes:
            if (inner == prefix or inner.startswith(prefix + ".")) and len(prefix) > best:
                best, found = len(prefix), layer
    return found


def imports(path: Path):
    """(imported module, names taken from it, line) for every import in the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, (), node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[: len(anchor) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in MODULES:  # "from package import submodule"
                    yield sub, (), node.lineno
                else:
                    yield base, (alias.name,), node.lineno


def internal_edges():
    for name, path in MODULES.items():
        for target, names, line in imports(path):
            if target == "affinebody" or target.startswith("affinebody."):
                yield name, target, names, line


def test_every_module_has_a_layer():
    missing = [m for m in MODULES if m != "affinebody" and layer_of(m) is None]
    assert not missing, f"give these modules a layer in LAYERS: {missing}"


def test_imports_go_down_the_layers():
    wrong = []
    for source, target, _, line in internal_edges():
        if target == "affinebody":  # the package root holds only the version and the API
            continue
        a, b = layer_of(source), layer_of(target)
        if a != b and b not in ALLOWED[a]:
            wrong.append(f"{source}:{line} ({a}) imports {target} ({b})")
    assert not wrong, "\n".join(wrong)


@pytest.mark.parametrize("layer", LIBRARY)
def test_the_library_never_imports_the_tooling(layer):
    wrong = []
    for name, path in MODULES.items():
        if layer_of(name) != layer:
            continue
        for target, _, line in imports(path):
            if target.split(".")[0] in TOOLING:
                wrong.append(f"{name}:{line} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_no_private_name_is_imported_across_modules():
    wrong = [f"{source}:{line} imports {n} from {target}"
             for source, target, names, line in internal_edges()
             for n in names if n.startswith("_") and not n.startswith("__") and target != source]
    assert not wrong, "\n".join(wrong)


def test_pytree_classes_are_registered_by_the_one_pytree_convention():
    """Only ``_pytree`` registers pytree nodes, and never through
    ``jax.tree_util.register_dataclass``, whose treedefs of different classes compare equal
    under jaxlib 0.10.1 (docs/architecture.md, "The pytree convention")."""
    wrong = []
    for name, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            called = node.func if isinstance(node, ast.Call) else None
            label = getattr(called, "attr", getattr(called, "id", ""))
            if label == "register_dataclass" or (
                    label.startswith("register_pytree") and name != "affinebody._pytree"):
                wrong.append(f"{name}:{node.lineno} calls {label}")
    assert not wrong, "\n".join(wrong)


def test_the_import_graph_has_no_cycle():
    graph: dict[str, set[str]] = {m: set() for m in MODULES}
    for source, target, _, _ in internal_edges():
        while target not in MODULES and "." in target:  # a name imported from a module
            target = target.rpartition(".")[0]
        # a package's __init__ importing its own submodules is how packages re-export
        if target != source and not target.startswith(source + "."):
            graph[source].add(target)
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module)


def test_the_public_api_resolves_and_import_stays_light():
    """Every name of affinebody.__all__ resolves to the object of its module; importing the
    package alone loads none of them (the command line starts quickly)."""
    import importlib
    import subprocess
    import sys

    import affinebody

    for name in affinebody.__all__:
        assert getattr(affinebody, name) is not None, name
    for name, (module, attribute) in affinebody._API.items():
        assert getattr(affinebody, name) is getattr(importlib.import_module(module), attribute)
    code = ("import sys, affinebody; "
            "print(sorted(m for m in sys.modules if m.startswith(('jax', 'affinebody.'))))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True).stdout.strip()
    assert loaded == "[]", loaded


def _public_definitions(tree: ast.Module) -> list[str]:
    names = []
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.append(node.name)
        elif isinstance(node, ast.Assign):
            names += [t.id for t in node.targets if isinstance(t, ast.Name)]
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.append(node.target.id)
    return [n for n in names if not n.startswith("_")]


def _imported_names(tree: ast.Module) -> set[str]:
    return {(alias.asname or alias.name).split(".")[0] for node in ast.walk(tree)
            if isinstance(node, (ast.Import, ast.ImportFrom)) for alias in node.names}


@pytest.mark.parametrize("path", sorted(
    p for p in PACKAGE.rglob("*.py")
    if p.name != "__init__.py" and not any(part.startswith("_")
                                           for part in p.relative_to(PACKAGE).parts)),
    ids=lambda p: str(p.relative_to(PACKAGE)))
def test_every_public_module_lists_its_public_names_in_all(path):
    """docs/architecture.md: each public module lists its names in ``__all__``: every public
    function and class is listed (constants may be), and every listed name is defined or
    imported there."""
    tree = ast.parse(path.read_text())
    listed = [node for node in tree.body
              if (isinstance(node, ast.Assign) and any(
                  isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets))
              or (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                  and node.target.id == "__all__")]
    assert len(listed) == 1, f"{path.name}: no __all__ (or more than one)"
    names = set(ast.literal_eval(listed[0].value))
    callables = {node.name for node in tree.body
                 if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                 and not node.name.startswith("_")}
    assert not callables - names, f"{path.name}: not in __all__: {sorted(callables - names)}"
    unknown = names - set(_public_definitions(tree)) - _imported_names(tree)
    assert not unknown, f"{path.name}: __all__ names what it does not define: {sorted(unknown)}"
