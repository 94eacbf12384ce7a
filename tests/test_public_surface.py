"""The public surface is marked: a module's `__all__` names what it exports, and the benchmark
scripts reach the library through public names only.

Read from the sources, not imported: the check costs no torch import.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("xvoe", "inference")


def module_path(module: str, root: Path = ROOT) -> Path | None:
    """The source of a dotted module of the repository (xvoe.inference is the inference folder)."""
    parts = module.split(".")
    if parts[:2] == ["xvoe", "inference"]:
        parts = parts[1:]
    base = root.joinpath(*parts)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.exists():
            return path
    return None


def exports(tree: ast.Module) -> list[str] | None:
    """The module's `__all__` where it is written out; None where it has none or computes it
    (xvoe's own, from its table of public names)."""
    for node in tree.body:
        if isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                try:
                    return list(ast.literal_eval(node.value))
                except ValueError:
                    return None
    return None


def top_level(tree: ast.Module) -> tuple[set[str], set[str]]:
    """(every name bound at the top level, the functions and classes defined there)."""
    bound, defined = set(), set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            defined.add(node.name)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            bound |= {(alias.asname or alias.name).split(".")[0] for alias in node.names}
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            bound |= {name.id for target in targets for name in ast.walk(target) if isinstance(name, ast.Name)}
    return bound | defined, defined


def is_face(path: Path, tree: ast.Module) -> bool:
    """A package's face (an __init__.py that defines nothing) or `python -m`'s entry: no surface of its own."""
    return path.name == "__main__.py" or (path.name == "__init__.py" and not top_level(tree)[1])


def export_problems(path: Path) -> list[str]:
    """A module without `__all__`; a name `__all__` lists that the module lacks; a public function or
    class it leaves out."""
    tree = ast.parse(path.read_text())
    listed = exports(tree)
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    if listed is None:
        computed = any(isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "__all__" for t in node.targets)
                       for node in tree.body)
        return [] if computed or is_face(path, tree) else [f"{where}: no __all__ says what it exports"]
    bound, defined = top_level(tree)
    lazy = "__getattr__" in defined         # its names load on first use (PEP 562): xvoe's own
    problems = [f"{where}: __all__ lists {name}, which it does not define"
                for name in listed if name not in bound and not lazy]
    problems += [f"{where}: {name} is public but not in __all__ (export it, or name it _{name})"
                 for name in sorted(defined - set(listed)) if not name.startswith("_")]
    return problems


def private_imports(script: Path, root: Path = ROOT) -> list[str]:
    """Each name a script imports from the library that is internal: `_name`, or left out of
    its module's `__all__`."""
    found = []
    for node in ast.walk(ast.parse(script.read_text())):
        if not isinstance(node, ast.ImportFrom) or not (node.module or "").startswith(PACKAGES):
            continue
        home = module_path(node.module, root)
        listed = exports(ast.parse(home.read_text())) if home else None
        for alias in node.names:
            if module_path(f"{node.module}.{alias.name}", root):
                continue                            # a module, not a name in one
            if alias.name.startswith("_") or (listed is not None and alias.name not in listed):
                found.append(f"{script.name}:{node.lineno} imports {node.module}.{alias.name}, an internal")
    return found


def test_every_all_names_what_its_module_exports():
    paths = [path for package in PACKAGES for path in sorted((ROOT / package).rglob("*.py"))]
    assert paths
    assert [problem for path in paths for problem in export_problems(path)] == []


def test_the_benchmarks_import_public_names_only():
    scripts = sorted((ROOT / "benchmarks").glob("*.py"))
    assert scripts
    assert [problem for script in scripts for problem in private_imports(script)] == []


def test_an_internal_import_and_a_stale_all_are_caught(tmp_path):
    (tmp_path / "xvoe").mkdir()
    (tmp_path / "xvoe" / "low.py").write_text('__all__ = ["shown", "gone"]\n\n\ndef shown(): ...\n\n\n'
                                              'def hidden(): ...\n\n\ndef _inner(): ...\n')
    (tmp_path / "xvoe" / "bare.py").write_text("def shown(): ...\n")
    script = tmp_path / "bench.py"
    script.write_text("from xvoe.low import _inner, hidden, shown\n")
    assert private_imports(script, tmp_path) == ["bench.py:1 imports xvoe.low._inner, an internal",
                                                 "bench.py:1 imports xvoe.low.hidden, an internal"]
    assert export_problems(tmp_path / "xvoe" / "low.py") == [
        f"{tmp_path / 'xvoe' / 'low.py'}: __all__ lists gone, which it does not define",
        f"{tmp_path / 'xvoe' / 'low.py'}: hidden is public but not in __all__ (export it, or name it _hidden)"]
    bare = tmp_path / "xvoe" / "bare.py"
    assert export_problems(bare) == [f"{bare}: no __all__ says what it exports"]
