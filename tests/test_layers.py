"""The import contract (docs/design.md, "Layers"): layers import downhill only, at the top of
a module, with no cycle; the benchmark layer needs no torch."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("xvoe", "inference")
# lowest first; a module's layer is that of the longest prefix listed
LAYERS = {
    "xvoe.errors": 0,
    "xvoe.allocator": 0,
    "xvoe.outputs": 0,
    "xvoe.processes": 0,
    "xvoe.resources": 0,
    "xvoe.domains": 0,
    "xvoe.progress": 0,
    "xvoe.scenes": 1,
    "xvoe.fingerprints": 1,         # hashes splits, read through the store
    "xvoe.models": 2,
    "xvoe.training": 3,
    "xvoe.evaluation": 4,
    "inference": 5,
    "xvoe.inference": 5,        # the same folder as it is imported (xvoe/inference links to it)
    "xvoe.apps": 6,
    "xvoe": 7,          # the package itself: the public API, over the layers
    "xvoe.cli": 8,      # the command, a client of the public API as a notebook is
    "xvoe.__main__": 8,
    "xvoe.examples": 8,         # models of one's own over the public API
}


# modules that import inside a function on purpose, downhill still: the package's public names and
# what the command's verbs need of torch load on first use, so that `import xvoe` and `xvoe --help`
# stay free of torch
DEFERRED = ("xvoe", "xvoe.cli", "xvoe.cli.arguments", "xvoe.cli.train")


def layer_of(module: str, layers: dict[str, int] = LAYERS) -> int:
    owners = [prefix for prefix in layers if module == prefix or module.startswith(prefix + ".")]
    if not owners:
        raise AssertionError(f"{module} belongs to no layer; add it to LAYERS")
    return layers[max(owners, key=len)]


def module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def internal_imports(path: Path, root: Path, packages: tuple[str, ...]) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) for every import of the packages in one file."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text())
    # `if TYPE_CHECKING:` imports are the module's own, for editors and type checkers
    checking = [node.body for node in tree.body if isinstance(node, ast.If) and _names_type_checking(node.test)]
    top_level = {id(node) for node in tree.body} | {id(node) for body in checking for node in body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            # `from pkg import sub` imports the submodule when there is one
            targets = [f"{stem}.{a.name}" if (root / f"{stem}.{a.name}".replace(".", "/")).with_suffix(".py").exists()
                       or (root / f"{stem}.{a.name}".replace(".", "/") / "__init__.py").exists() else stem
                       for a in node.names]
        else:
            continue
        for target in targets:
            if target.split(".")[0] in packages:
                found.append((target, node.lineno, id(node) in top_level))
    return found


def _names_type_checking(test: ast.expr) -> bool:
    return isinstance(test, ast.Name) and test.id == "TYPE_CHECKING"


def import_graph(root: Path, packages: tuple[str, ...]) -> dict[str, list[tuple[str, int, bool]]]:
    return {module_name(path, root): internal_imports(path, root, packages)
            for package in packages for path in sorted((root / package).rglob("*.py"))}


def violations(root: Path, packages: tuple[str, ...], layers: dict[str, int],
               deferred: tuple[str, ...] = ()) -> list[str]:
    """Every upward import, import inside a function or class (but in the modules `deferred`),
    and cycle, one line each."""
    graph = import_graph(root, packages)
    found = []
    for module, imports in graph.items():
        for target, line, top in imports:
            if layer_of(target, layers) > layer_of(module, layers):
                found.append(f"{module}:{line} imports {target}, a higher layer")
            if not top and module not in deferred:
                found.append(f"{module}:{line} imports {target} inside a function or class")
    edges = {m: {t for t, _, _ in imports if t in graph and t != m} for m, imports in graph.items()}
    found += [f"import cycle: {' -> '.join(cycle)}" for cycle in cycles(edges)]
    return found


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, result = {}, {}, [], set(), []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in edges.get(node, ()):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                result.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return result


def test_the_package_keeps_its_layers():
    assert violations(ROOT, PACKAGES, LAYERS, DEFERRED) == []


def plant(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_an_upward_import_is_caught(tmp_path):
    root = plant(tmp_path, {"pkg/__init__.py": "", "pkg/low.py": "from .high import thing\n",
                            "pkg/high.py": "thing = 1\n"})
    found = violations(root, ("pkg",), {"pkg": 9, "pkg.low": 0, "pkg.high": 1})
    assert found == ["pkg.low:1 imports pkg.high, a higher layer"]


def test_an_import_inside_a_function_and_a_cycle_are_caught(tmp_path):
    root = plant(tmp_path, {"pkg/__init__.py": "", "pkg/a.py": "from pkg import b\n",
                            "pkg/b.py": "def f():\n    from . import a\n"})
    found = violations(root, ("pkg",), {"pkg": 0})
    assert "pkg.b:2 imports pkg.a inside a function or class" in found
    assert "import cycle: pkg.a -> pkg.b" in found
    allowed = violations(root, ("pkg",), {"pkg": 0}, deferred=("pkg.b",))
    assert allowed == ["import cycle: pkg.a -> pkg.b"]


def test_the_benchmark_layer_runs_without_torch():
    code = ("import sys; import xvoe.scenes.generate, xvoe.scenes.custom, xvoe.scenes.videos; "
            "print('torch' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert done.stdout.strip() == "False"


def public_homes() -> tuple[dict[str, str], dict[str, str], list[str]]:
    """xvoe/__init__.py's public names -> the module they are read from, as its `if TYPE_CHECKING:`
    block imports them and as `_home` imports that module on first use; and its `__all__`."""
    tree = ast.parse((ROOT / "xvoe" / "__init__.py").read_text())

    def stem(node: ast.ImportFrom) -> str:
        return "xvoe" + ("." + node.module if node.module else "")

    checking = {alias.asname or alias.name: stem(imported) for node in tree.body
                if isinstance(node, ast.If) and _names_type_checking(node.test) for imported in node.body
                for alias in imported.names}
    function = next(node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == "_home")
    lazy = {}
    for case in next(node for node in function.body if isinstance(node, ast.Match)).cases:
        names = [c.value.value for c in ast.walk(case.pattern) if isinstance(c, ast.MatchValue)]
        homes = [f"{stem(node)}.{alias.name}" for node in case.body if isinstance(node, ast.ImportFrom)
                 for alias in node.names if alias.asname == "home"]
        lazy |= dict.fromkeys(names, homes[0] if homes else None)
    listed = next(node.value for node in tree.body if isinstance(node, ast.Assign)
                  and node.targets[0].id == "__all__")
    return checking, lazy, [item.value for item in listed.elts]


def test_the_public_names_are_imported_alike_for_editors_and_on_first_use():
    checking, lazy, listed = public_homes()
    assert len(checking) > 50 and lazy == checking and listed == sorted(checking)


def test_import_xvoe_leaves_torch_out():
    done = subprocess.run([sys.executable, "-c", "import sys, xvoe; xvoe.XvoeError; print('torch' in sys.modules)"],
                          capture_output=True, text=True, check=True, cwd=ROOT)
    assert done.stdout.strip() == "False"
