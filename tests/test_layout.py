"""The package layout is the pipeline: model -> forward -> tracks -> fitting -> show -> app.

Read from the source (``ast``), not by importing: every estim import, at module level or
inside a function, goes to the same layer or an earlier one (so there is no import cycle
between layers), modules of one layer import each other without a cycle, no name with a
leading underscore is imported from another layer, and an import inside a function says
why on its own line (``# lazy: ...``): only the modules that pull in matplotlib or MuJoCo
may stay lazy, so that ``import estim`` does not load them.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "estim"
# The pipeline, earliest first. "" is estim's own top level (configuration, JSON).
LAYERS = ("", "model", "forward", "tracks", "fitting", "show", "app")


def _module_name(path: pathlib.Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else ""


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports():
    """(importer, imported module, names, line, lazy, source line) for every estim import."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = _module_name(path)
        source = path.read_text()
        lines = source.splitlines()
        tree = ast.parse(source)
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        nested = {id(c) for f in functions for c in ast.walk(f) if c is not f}
        for node in ast.walk(tree):
            lazy = id(node) in nested
            if isinstance(node, ast.ImportFrom):
                target = _resolve(module, path.name == "__init__.py", node)
                if target == "estim" or target.startswith("estim."):
                    for alias in node.names:
                        sub = f"{target}.{alias.name}"
                        # `from . import _native` imports a module, not a name
                        is_module = (PACKAGE.parent / sub.replace(".", "/")).with_suffix(".py").exists() or (
                            PACKAGE.parent / sub.replace(".", "/")
                        ).is_dir()
                        out.append((module, sub if is_module else target, None if is_module else alias.name,
                                    node.lineno, lazy, lines[node.lineno - 1]))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name == "estim" or alias.name.startswith("estim."):
                        out.append((module, alias.name, None, node.lineno, lazy, lines[node.lineno - 1]))
    return out


IMPORTS = _imports()


def test_the_walk_finds_the_pipeline():
    importers = {imp for imp, *_ in IMPORTS}
    assert {"estim.forward._simulate", "estim.fitting._fit", "estim.app._cli"} <= importers
    assert {_layer(m) for m in importers} == set(LAYERS)


def test_imports_go_down_the_pipeline():
    """An import of a later layer would be a cycle through the package's order."""
    bad = [
        f"{imp}:{line} imports {target} (layer '{_layer(target)}' comes after '{_layer(imp)}')"
        for imp, target, _, line, _, _ in IMPORTS
        if target not in ("estim",) and LAYERS.index(_layer(target)) > LAYERS.index(_layer(imp))
    ]
    # estim/__init__.py gathers the public API from every layer; __main__ is the command.
    bad = [b for b in bad if not b.startswith(("estim:", "estim.__main__:"))]
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    graph: dict[str, set[str]] = {}
    for imp, target, *_ in IMPORTS:
        if target != "estim" and imp != "estim":
            graph.setdefault(imp, set()).add(target)
    seen, on_stack = set(), []

    def visit(m):
        if m in on_stack:
            cycle = on_stack[on_stack.index(m):] + [m]
            pytest.fail("import cycle: " + " -> ".join(cycle))
        if m in seen:
            return
        on_stack.append(m)
        for t in sorted(graph.get(m, ())):
            visit(t)
        on_stack.pop()
        seen.add(m)

    for m in sorted(graph):
        visit(m)


def test_no_private_name_across_layers():
    bad = [
        f"{imp}:{line} imports {name} from {target}"
        for imp, target, name, line, _, _ in IMPORTS
        if name and name.startswith("_") and _layer(target) != _layer(imp)
    ]
    assert not bad, "\n".join(bad)


def test_lazy_imports_say_why():
    bad = [f"{imp}:{line}: {src.strip()}" for imp, _, _, line, lazy, src in IMPORTS
           if lazy and "# lazy:" not in src]
    assert not bad, "estim imports inside functions without '# lazy: reason':\n" + "\n".join(bad)


def test_the_package_imports_no_plotting_or_mujoco_viewer():
    """``import estim`` stays light: matplotlib is loaded by the plots only (checked in a
    fresh interpreter, since the test session may have loaded it already)."""
    import subprocess
    import sys

    code = "import sys, estim; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
