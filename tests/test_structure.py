"""The source tree's shape, read from its syntax trees: clrefract's modules import one another
without cycles, and no module reaches into another's private names. Imports inside functions
count as much as those at the top of a file."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def module_name(path: Path) -> str:
    """clrefract/fields/base.py -> clrefract.fields.base; a package's __init__.py -> the package."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def sources(*folders: str) -> dict[str, Path]:
    """Module name -> file, for every .py under the folders."""
    return {module_name(p): p for f in folders for p in sorted((ROOT / f).rglob("*.py"))}


def imports(path: Path, modules: set[str]):
    """(line, module imported from, name or None) for each import in the file, relative ones
    resolved; `from .x import y` names module x.y where y is a submodule, else x with name y."""
    here = module_name(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            base = ".".join(base + (node.module.split(".") if node.module else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in modules:
                    yield node.lineno, sub, None
                else:
                    yield node.lineno, base, alias.name


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module, each sorted."""

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for m in graph[todo.pop()] - seen:
                seen.add(m)
                todo.append(m)
        return seen

    reachable = {m: reach(m) for m in graph}
    parts = {tuple(sorted(n for n in reachable[m] if m in reachable[n])) for m in graph}
    return sorted(list(p) for p in parts if len(p) > 1)


def private(name: str) -> bool:
    """A name with a leading underscore; dunders (`__version__`) are public."""
    dunder = name.startswith("__") and name.endswith("__")
    return name.startswith("_") and not dunder


def test_no_import_cycles_in_the_package():
    files = sources("clrefract")
    graph, where = {m: set() for m in files}, {}
    for m, path in files.items():
        for line, target, _ in imports(path, set(files)):
            if target in files and target != m:
                graph[m].add(target)
                where.setdefault((m, target), f"{path.relative_to(ROOT)}:{line}")
    found = cycles(graph)
    report = [
        " <-> ".join(c)
        + "".join(f"\n    {a} -> {b} ({where[a, b]})" for a in c for b in c if b in graph[a])
        for c in found
    ]
    assert not found, "import cycles:\n" + "\n".join(report)


def test_no_module_imports_another_modules_private_name():
    files = sources("clrefract", "tools", "tests")
    modules = set(files)
    bad = [
        f"{path.relative_to(ROOT)}:{line}: from {target} import {name}"
        for path in files.values()
        for line, target, name in imports(path, modules)
        if name and private(name) and target.split(".")[0] == "clrefract"
    ]
    assert not bad, "private names imported from another module:\n" + "\n".join(bad)


KINDS = {"voxel", "levelset", "hashgrid", "interface", "auto"}


def names_compared(node: ast.Compare) -> set[str]:
    """The string constants a comparison tests against (alone, or in a tuple, list or set)."""
    found = set()
    for side in [node.left, *node.comparators]:
        items = side.elts if isinstance(side, ast.Tuple | ast.List | ast.Set) else [side]
        found |= {
            i.value for i in items if isinstance(i, ast.Constant) and isinstance(i.value, str)
        }
    return found


def test_only_the_field_adapters_branch_on_the_field_kind():
    """The fit asks its adapter (clrefract/fit/kinds.py), as the tracer asks a field for its
    kernels: no other module compares anything with a kind's name. Fields name their own
    kind (fields/), and the kinds' adapters are the one table of them."""
    allowed = {"clrefract.fit.kinds"}
    files = {m: p for m, p in sources("clrefract").items() if not m.startswith("clrefract.fields")}
    bad = [
        f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}"
        for m, path in files.items()
        if m not in allowed
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Compare) and names_compared(node) & KINDS
    ]
    assert not bad, "branches on the field kind outside its adapter:\n" + "\n".join(bad)


def test_no_private_name_of_the_fit_is_reached_from_another_module():
    """A private attribute or method of the fit's objects (clrefract/fit/) is used only in
    the module that defines it, on `self`."""
    fit_files = sources("clrefract/fit")
    defined = {}
    for m, path in fit_files.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.ClassDef) and private(node.name):
                defined.setdefault(node.name, set()).add(m)
            if isinstance(node, ast.Attribute) and private(node.attr):
                if isinstance(node.value, ast.Name) and node.value.id == "self":
                    defined.setdefault(node.attr, set()).add(m)
    bad = []
    for m, path in sources("clrefract", "tools", "tests").items():
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Attribute) and node.attr in defined):
                continue
            on_self = isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")
            if not (on_self and m in defined[node.attr]):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    assert not bad, "the fit's private names reached from outside:\n" + "\n".join(bad)


def test_the_library_reaches_no_private_attribute_but_its_own():
    """Within clrefract/, a private attribute is read only on `self` or `cls`: no module
    reaches into another object's private state (argparse's formatter classes aside, which
    a help formatter must name)."""
    bad = [
        f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}"
        for path in sources("clrefract").values()
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Attribute)
        and private(node.attr)
        and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls", "argparse"))
        and not (isinstance(node.value, ast.Call) and ast.unparse(node.value.func) == "super")
    ]
    assert not bad, "private attributes reached from outside:\n" + "\n".join(bad)


def test_every_package_is_in_the_wheel():
    """A plain (non-editable) install holds only the packages pyproject.toml lists: a package
    left out imports from a checkout but not from a user's site-packages."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(setup["packages"])
    found = {module_name(p) for p in (ROOT / "clrefract").rglob("__init__.py")}
    assert found - listed == set(), f"pyproject.toml's packages leave out {sorted(found - listed)}"
