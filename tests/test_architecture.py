"""The package layout, checked on the syntax tree of every module (imports inside functions too).

- ``pipeline`` is the core (config, schema, store, executors, metrics, ...): none of its modules
  imports a stage (``render``, ``clean``, ``train``, ``evaluate``), except the command line
  ``pipeline/cli.py``, which only dispatches to them.
- No module uses another module's private (``_underscore``) name, by ``from m import _name`` or as
  ``m._name``: what a module shares is public.
- Project modules are imported through the one installed name, ``mcdenoise.pipeline.config`` (or
  relatively inside a package), never as a top-level ``pipeline.config``: that name works only in a
  source checkout and would load a second copy of the module there. A package's ``__main__`` (run as
  ``python -m pipeline``, whose package is then the top-level ``pipeline``) imports absolutely.
  The checks below name modules without the ``mcdenoise.`` prefix.
- Test modules share fixtures through ``tests/conftest.py`` and helpers through ``tests/helpers.py``,
  never by importing another test module (its module-scoped fixtures would run once more there).
- Each package's docstring names every module of the package.
- Every subcommand of ``python -m pipeline`` is declared in one module, ``pipeline/cli.py``; every call
  builds every parser, so it loads no torch, numpy or Mitsuba.
- No import cycle between project modules, counting the imports inside functions: a function-level
  import only defers the cycle to the first call, and two modules that need each other are one
  idea cut in two (move what both need to where it belongs). ``from package import module`` is an
  edge to that module; any other import an edge to the module it names.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE = "pipeline"
STAGES = ("render", "clean", "train", "evaluate")
DISPATCH = {"pipeline.cli"}
PACKAGE = "mcdenoise"   # the installed name; pyproject.toml maps the folders above under it


def modules() -> dict[str, Path]:
    out = {}
    for pkg in (CORE, *STAGES):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _project(name: str) -> str:
    """``mcdenoise.pipeline.config`` -> ``pipeline.config``; other names as they are."""
    return name.removeprefix(PACKAGE + ".")


def _absolute(module: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return _project(node.module or "")
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = package[: len(package) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def imports(module: str, path: Path) -> list[tuple[str, str | None, int]]:
    """(imported module, imported name or None, line) for every import statement of the module."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(_project(a.name), None, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module == PACKAGE:
            out += [(a.name, None, node.lineno) for a in node.names]     # from mcdenoise import render
        elif isinstance(node, ast.ImportFrom):
            src = _absolute(module, path, node)
            out += [(src, a.name, node.lineno) for a in node.names]
    return sorted(out, key=lambda x: x[2])


def unprefixed_imports(path: Path) -> list[str]:
    """Imports of a project folder by its bare top-level name (``from pipeline.x import``), and relative
    imports in a ``__main__.py`` of one."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                 [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
        found += [f"{path.relative_to(ROOT)}:{node.lineno}: {n}" for n in names if n.split(".")[0] in (CORE, *STAGES)]
        if isinstance(node, ast.ImportFrom) and node.level and path.name == "__main__.py":
            found.append(f"{path.relative_to(ROOT)}:{node.lineno}: relative import in a __main__")
    return found


def private_uses(module: str, path: Path, known: set[str]) -> list[str]:
    """``from m import _x`` and ``alias._x`` where ``alias`` names another project module."""
    tree = ast.parse(path.read_text(), str(path))
    aliases: dict[str, str] = {}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.asname and _project(a.name) in known:
                    aliases[a.asname] = _project(a.name)
        elif isinstance(node, ast.ImportFrom):
            src = _absolute(module, path, node)
            for a in node.names:
                full = f"{src}.{a.name}"
                if full in known:                       # from package import module [as alias]
                    aliases[a.asname or a.name] = full
                elif src in known and a.name.startswith("_") and not a.name.startswith("__") and src != module:
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: from {src} import {a.name}")
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                and node.attr.startswith("_") and not node.attr.startswith("__")):
            found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {aliases[node.value.id]}.{node.attr}")
    return found


MODULES = modules()


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m.split(".")[0] == CORE and m not in DISPATCH))
def test_core_imports_no_stage(module):
    bad = [f"line {line}: {src}" for src, _, line in imports(module, MODULES[module]) if src.split(".")[0] in STAGES]
    assert not bad, f"{module} (core) imports a stage: " + "; ".join(bad)


def test_every_stage_is_dispatched_by_the_command_line_only():
    """The command line is the one core module that may import stages (to dispatch)."""
    stages = {src.split(".")[0] for src, _, _ in imports("pipeline.cli", MODULES["pipeline.cli"])}
    assert stages & set(STAGES)


def test_no_module_uses_another_modules_private_names():
    known = set(MODULES)
    found = [hit for m, p in MODULES.items() for hit in private_uses(m, p, known)]
    assert not found, "private names used outside their module:\n" + "\n".join(found)


def test_project_modules_are_imported_through_the_installed_name():
    paths = [*MODULES.values(), *sorted((ROOT / "tests").glob("*.py")), *sorted((ROOT / PACKAGE).glob("*.py"))]
    found = [hit for path in paths for hit in unprefixed_imports(path)]
    assert not found, f"imports that bypass {PACKAGE}. (run the import rewrite):\n" + "\n".join(found)


def test_test_modules_do_not_import_each_other():
    found = []
    for path in sorted((ROOT / "tests").glob("test_*.py")):
        module = f"tests.{path.stem}"
        found += [f"{path.name}:{line}: {src}" for src, _, line in imports(module, path)
                  if src.startswith("tests.test_") and src != module]
    assert not found, "test modules importing other test modules:\n" + "\n".join(found)


def import_graph(mods: dict[str, Path]) -> dict[str, dict[str, int]]:
    """module -> {project module it imports: line of the first such import}, imports in functions too."""
    graph: dict[str, dict[str, int]] = {}
    for module, path in mods.items():
        row = graph.setdefault(module, {})
        for src, name, line in imports(module, path):
            target = f"{src}.{name}" if name and f"{src}.{name}" in mods else src
            if target in mods and target != module:
                row.setdefault(target, line)
    return graph


def import_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted; sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_no_import_cycle_between_modules():
    graph = import_graph(MODULES)
    lines = []
    for cycle in import_cycles(graph):
        lines.append(" <-> ".join(cycle) + ": " + "; ".join(
            f"{MODULES[a].relative_to(ROOT)}:{graph[a][b]} imports {b}" for a in cycle for b in cycle if b in graph[a]))
    assert not lines, "import cycles between modules:\n" + "\n".join(lines)


@pytest.mark.parametrize("package", [CORE, *STAGES])
def test_every_package_docstring_names_each_of_its_modules(package):
    """A package's docstring is its table of contents: each module appears as ````package.module````."""
    doc = ast.get_docstring(ast.parse((ROOT / package / "__init__.py").read_text())) or ""
    missing = [m for m in sorted(MODULES) if m.split(".")[0] == package and m != package and f"``{m}``" not in doc]
    assert not missing, f"{package}/__init__.py does not name: " + ", ".join(missing)


def test_the_checker_sees_what_it_forbids(tmp_path):
    """The checks above must be able to fail: a core module importing a stage inside a function,
    and a private name used through a module alias, are found."""
    core = tmp_path / "core.py"
    core.write_text("def f():\n    from mcdenoise.render.frame import FrameTask\n    from . import color as c\n"
                    "    from mcdenoise import clean\n    return c._clamp\n")
    assert [src for src, _, _ in imports("pipeline.core", core)] == ["render.frame", "pipeline", "clean"]
    main = tmp_path / "__main__.py"
    main.write_text("import mcdenoise.pipeline.exr as exr\nfrom train.model import load\nfrom .config import Config\n")
    global ROOT
    old, ROOT = ROOT, tmp_path
    try:
        assert private_uses("pipeline.core", core, {"pipeline.color", "render.frame"}) == ["core.py:5: pipeline.color._clamp"]
        assert unprefixed_imports(main) == ["__main__.py:2: train.model", "__main__.py:3: relative import in a __main__"]
    finally:
        ROOT = old


def test_the_cycle_check_sees_imports_inside_functions(tmp_path):
    """A cycle closed by an import inside a function is found (and only the modules on it); a chain is not a cycle."""
    (tmp_path / "a.py").write_text("from . import b\nfrom .c import X\n")
    (tmp_path / "b.py").write_text("def f():\n    from mcdenoise.clean.a import Y\n    return Y\n")
    (tmp_path / "c.py").write_text("import numpy\nX = 1\n")
    mods = {f"clean.{n}": tmp_path / f"{n}.py" for n in "abc"}
    graph = import_graph(mods)
    assert graph == {"clean.a": {"clean.b": 1, "clean.c": 2}, "clean.b": {"clean.a": 2}, "clean.c": {}}
    assert import_cycles(graph) == [["clean.a", "clean.b"]]
    (tmp_path / "b.py").write_text("def f():\n    from .c import X\n    return X\n")
    assert import_cycles(import_graph(mods)) == []


def test_the_command_line_builds_its_parser_without_torch():
    """``pipeline.cli`` declares every subcommand, and every call builds every parser: it loads no torch,
    numpy or Mitsuba (a handler imports what its command runs)."""
    import subprocess
    import sys

    code = ("import sys; from mcdenoise.pipeline.cli import build_parser; build_parser(); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'numpy', 'mitsuba', 'drjit'}))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert proc.stdout.strip() == "[]"


def package_graph() -> dict[str, dict[str, int]]:
    """package -> {imported package: number of module-to-module import edges} (imports in functions too)."""
    graph: dict[str, dict[str, int]] = {}
    for module, path in MODULES.items():
        targets = {src for src, _, _ in imports(module, path)}
        for pkg in {t.split(".")[0] for t in targets} & {CORE, *STAGES} - {module.split(".")[0]}:
            n = len({t for t in targets if t.split(".")[0] == pkg})
            row = graph.setdefault(module.split(".")[0], {})
            row[pkg] = row.get(pkg, 0) + n
    return graph


if __name__ == "__main__":   # python tests/test_architecture.py: the import graph, for people
    for pkg, row in sorted(package_graph().items()):
        print(f"{pkg:9s} -> " + ", ".join(f"{k} ({v})" for k, v in sorted(row.items())))
    core = sorted(m for m, p in MODULES.items() if m.split(".")[0] == CORE and m not in DISPATCH
                  and any(src.split(".")[0] in STAGES for src, _, _ in imports(m, p)))
    print("core modules importing a stage:", ", ".join(core) or "none")
