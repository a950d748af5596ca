"""The package's layers: a module imports only modules of its own layer or of lower ones, and no two
modules import each other, directly or through others (docs/architecture.md draws the layers)."""
from __future__ import annotations

import ast
import re
from pathlib import Path

from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "scope3d"

# lowest first; a layer may import those before it (the same rank shares a level)
RANK = {"errors": 0, "utils": 0, "geometry": 1, "sensor": 2, "scene": 3, "io": 4, "phantoms": 5, "feature": 6,
        "estimators": 7, "sfm": 8, "mvs": 8, "registration": 8, "metrology": 8, "pipelines": 9, "report": 10,
        "cli": 11}


def _modules() -> dict[str, Path]:
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = list(f.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


def _imports(module: str, path: Path) -> set[str]:
    """Every scope3d module ``module`` imports, at the top or inside functions (``from package import
    submodule`` counts as importing the submodule only)."""
    known = _modules()
    found = set()
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            if base.startswith("scope3d"):
                for a in node.names:
                    found.add(f"{base}.{a.name}" if f"{base}.{a.name}" in known else base)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("scope3d"))
    return found


def test_every_top_level_part_has_a_layer():
    assert {m.split(".")[1] for m in _modules() if m.count(".") >= 1} <= set(RANK)


def test_no_module_imports_a_higher_layer():
    bad = []
    for module, path in _modules().items():
        if module == "scope3d":
            continue
        layer = module.split(".")[1]
        for other in _imports(module, path):
            if other == "scope3d" or other.split(".")[1] == layer:  # the package's version, its own layer
                continue
            if RANK[other.split(".")[1]] >= RANK[layer]:
                bad.append(f"{module} imports {other}")
    assert not bad, "\n".join(bad)


def test_no_import_cycle_between_modules():
    modules = _modules()
    names = list(modules)
    index = {m: k for k, m in enumerate(names)}
    edges = [(index[m], index[o]) for m, p in modules.items() for o in _imports(m, p) if o in index and o != m]
    rows, cols = zip(*edges)
    graph = coo_matrix(([1] * len(edges), (rows, cols)), shape=(len(names), len(names)))
    n, labels = connected_components(graph, directed=True, connection="strong")
    # a package's __init__ re-exporting its modules is not a cycle (its modules import each other, not it)
    cycles = [sorted(names[k] for k in range(len(names)) if labels[k] == c) for c in range(n)
              if (labels == c).sum() > 1]
    assert not cycles, cycles


def _package(module: str) -> str:
    """The top-level package (``scope3d.estimators``) that a module belongs to: where its private names may go."""
    return ".".join(module.split(".")[:2])


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_crosses_a_package():
    """A private name is its own package's: ``from scope3d.a.b import _x``, ``b._x`` (``b`` a module of another
    package) and importing a private module (``scope3d.a._m``) are refused outside ``scope3d.a``; what two
    packages share is public."""
    known = _modules()
    bad = []
    for module, path in known.items():
        own = _package(module)
        package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
        tree = ast.parse(path.read_text())
        aliases = {}  # names bound to scope3d modules
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
                if not base.startswith("scope3d") or _package(base) == own:
                    continue
                if any(_private(part) for part in base.split(".")):
                    bad.append(f"{module} imports the private module {base}")
                for a in node.names:
                    if _private(a.name):
                        bad.append(f"{module} imports {base}.{a.name}")
                    elif f"{base}.{a.name}" in known:
                        aliases[a.asname or a.name] = f"{base}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("scope3d") and _package(a.name) != own:
                        if any(_private(part) for part in a.name.split(".")):
                            bad.append(f"{module} imports the private module {a.name}")
                        if a.asname:
                            aliases[a.asname] = a.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases):
                bad.append(f"{module} uses {aliases[node.value.id]}.{node.attr}")
    assert not bad, "\n".join(sorted(set(bad)))


ARCHITECTURE = PACKAGE.parents[1] / "docs" / "architecture.md"


def _diagram_by_layer() -> dict[str, str]:
    """The text of architecture.md's layer diagram (its first code block), by the layer each line describes:
    a line whose first word (after the diagram's ``│``) is a layer's name starts that layer's text."""
    block = ARCHITECTURE.read_text().split("```")[1]
    text: dict[str, str] = {}
    layer = None
    for line in block.splitlines():
        words = re.findall(r"[A-Za-z_]+", line.replace("│", " "))
        if words and words[0] in RANK:
            layer = words[0]
        if layer is not None:
            text[layer] = text.get(layer, "") + "\n" + line
    return text


def test_the_architecture_diagram_names_every_module_in_its_layer():
    # a module named nowhere on the newcomer's map is how the map drifted from the tree before (issue 31)
    text = _diagram_by_layer()
    missing = []
    for module in _modules():
        parts = module.split(".")[1:]
        if len(parts) < 2:  # the package and the layers themselves (errors is its own layer)
            assert not parts or parts[0] in text, f"layer {parts[0]} is not in docs/architecture.md's diagram"
            continue
        if not re.search(rf"(?<!\w){re.escape(parts[-1])}(?!\w)", text.get(parts[0], "")):
            missing.append(module)
    assert not missing, f"modules docs/architecture.md's diagram does not name in their layer: {missing}"


def test_every_package_docstring_names_modules_that_exist_and_no_future():
    # a package's docstring is the second thing a newcomer reads: it must not point at modules that are
    # gone or promise code that has landed
    modules = _modules()
    for package, path in modules.items():
        if path.name != "__init__.py":
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        assert doc, f"{package} has no docstring"
        assert "lands here" not in doc and "land here" not in doc, f"{package}'s docstring promises code"
        for name in re.findall(r":mod:`(\.?[\w.]+)`", doc):
            full = package + name if name.startswith(".") else name
            assert full in modules, f"{package}'s docstring names {name}, which is not a module"
