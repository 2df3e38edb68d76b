"""Architecture of affinebody.quantum (issue 14): no import cycle among its modules, no private
name imported across modules, and the library modules import nothing from affinebody but the
core and kinematics modules (config and cli are the application layer)."""

import ast
from pathlib import Path

QUANTUM = Path(__file__).resolve().parents[1] / "src" / "affinebody" / "quantum"
#: the application layer, allowed to import affinebody.config / affinebody.expressions
APPLICATION = {"config", "cli"}
#: core and kinematics modules of affinebody the quantum library may use
CORE = {"_checks", "_linalg", "groups", "polar", "deformation", "expressions", "state"}


def imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module imported, names imported from it) for every import in the file, at any depth."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.append((node.module, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
    return out


def quantum_edges() -> dict[str, set[str]]:
    """module -> the quantum modules it imports (``from affinebody.quantum import x`` too)."""
    modules = {p.stem for p in QUANTUM.glob("*.py")} - {"__init__"}
    edges = {m: set() for m in modules}
    for m in modules:
        for module, names in imports(QUANTUM / f"{m}.py"):
            if module == "affinebody.quantum":
                edges[m] |= set(names) & modules
            elif module.startswith("affinebody.quantum."):
                edges[m].add(module.rsplit(".", 1)[1])
    return edges


def test_no_import_cycle():
    edges = quantum_edges()
    assert {"levels", "bases", "n2", "spectra"} <= set(edges)
    state: dict[str, int] = {}

    def visit(m, path):
        state[m] = 1
        for d in edges[m]:
            assert state.get(d) != 1, f"import cycle: {' -> '.join(path + [m, d])}"
            if d not in state:
                visit(d, path + [m])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [])


def test_no_private_name_crosses_modules_and_layers_hold():
    for path in sorted(QUANTUM.glob("*.py")):
        for module, names in imports(path):
            if not module.startswith("affinebody"):
                continue
            private = [n for n in names if n.startswith("_")]
            assert not private, f"{path.name} imports private {private} from {module}"
            if module.startswith("affinebody.quantum") or module == "affinebody":
                allowed = module == "affinebody.quantum" or module.startswith(
                    "affinebody.quantum.") or set(names) <= CORE
                assert allowed, f"{path.name}: from affinebody import {names}"
                continue
            top = module.split(".")[1]
            if path.stem in APPLICATION:
                assert top in CORE | {"config"}, f"{path.name} imports {module}"
            else:
                assert top in CORE, f"{path.name} imports {module} (not core/kinematics)"


def test_public_modules_declare_all_and_no_lazy_shims():
    for path in sorted(QUANTUM.glob("*.py")):
        tree = ast.parse(path.read_text())
        top = [n for n in tree.body if isinstance(n, ast.FunctionDef)]
        assert "__getattr__" not in {f.name for f in top}, f"{path.name} has a lazy __getattr__"
        if path.stem in ("__init__", "densities"):
            continue
        declared = [n for n in tree.body if isinstance(n, ast.Assign)
                    and any(isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets)]
        assert declared, f"{path.name} has no __all__"
        names = ast.literal_eval(declared[0].value)
        defined = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        defined |= {t.id for n in tree.body if isinstance(n, ast.Assign) for t in n.targets
                    if isinstance(t, ast.Name)}
        defined |= {n.target.id for n in tree.body if isinstance(n, ast.AnnAssign)}
        defined |= {a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom)
                    for a in n.names}
        assert set(names) <= defined, f"{path.name}: __all__ names undefined"
