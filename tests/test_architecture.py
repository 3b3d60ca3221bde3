"""The house stays built: packages by stage importing only downward (the import-linter
contracts in pyproject.toml), no import cycle even through imports inside functions,
no module over 800 lines, every package saying what it is for, one front door."""

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dempipe"
MAX_LINES = 800


def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted(PACKAGE.rglob("*.py")):
        parts = list(p.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(name: str, path: Path, modules: dict) -> set[str]:
    """The dempipe modules ``name`` imports, at module level or inside functions."""
    is_pkg = path.name == "__init__.py"
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[:len(base) - (node.level - 1)]
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            for a in node.names:
                sub = f"{src}.{a.name}"
                found.add(sub if sub in modules else src)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in modules and m != name}


def test_no_import_cycles_counting_imports_inside_functions():
    modules = _modules()
    graph = {m: _imports(m, p, modules) for m, p in modules.items()}
    # Tarjan's strongly connected components: any of more than one module is a cycle
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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
                cycles.append(sorted(comp))

    for m in graph:
        if m not in index:
            visit(m)
    assert cycles == []
    # the root package is the front door: nothing inside imports it
    assert [m for m, deps in graph.items() if "dempipe" in deps] == []


def test_the_check_finds_a_cycle(tmp_path, monkeypatch):
    # negative control: two modules importing each other inside functions are a cycle
    pkg = tmp_path / "dempipe"
    (pkg / "a").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a" / "__init__.py").write_text("")
    (pkg / "a" / "x.py").write_text("def f():\n    from dempipe.a import y\n")
    (pkg / "a" / "y.py").write_text("def g():\n    from dempipe.a.x import f\n")
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", pkg)
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    with pytest.raises(AssertionError):
        test_no_import_cycles_counting_imports_inside_functions()


def test_layers_contracts_hold():
    exe = shutil.which("lint-imports", path=os.path.dirname(sys.executable)) \
        or shutil.which("lint-imports")
    if exe is None:
        pytest.skip("import-linter is not installed (pip install '.[test]')")
    proc = subprocess.run([exe, "--config", str(ROOT / "pyproject.toml")], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    assert f"Contracts: {len(contracts['contracts'])} kept, 0 broken." in proc.stdout


def test_every_package_is_installed_and_says_what_it_is_for():
    packages = sorted(".".join(p.parent.relative_to(ROOT).parts)
                      for p in PACKAGE.rglob("__init__.py"))
    listed = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    assert sorted(p for p in listed if p.startswith("dempipe.") or p == "dempipe") == packages
    for name in packages:
        init = ROOT.joinpath(*name.split(".")) / "__init__.py"
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc.splitlines()[0]) > 20, f"{name}: no one-line purpose"


def test_no_module_over_800_lines():
    long = {str(p.relative_to(ROOT)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_no_module_level_getattr_but_the_front_door():
    shims = [str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py")
             if p != PACKAGE / "__init__.py"
             and any(isinstance(n, ast.FunctionDef) and n.name == "__getattr__"
                     for n in ast.parse(p.read_text()).body)]
    assert shims == []


def _private_imports(path: Path, modules: dict) -> list[str]:
    """``module.name`` for each underscore name ``path`` takes from another dempipe
    module: imported by name, or read as an attribute of an imported module (a
    namedtuple's ``_fields`` and the like are public API, not private)."""
    tree = ast.parse(path.read_text())
    mods, out = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and not node.level and node.module \
                and node.module.split(".")[0] == "dempipe":
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                if sub in modules:
                    mods[a.asname or a.name] = sub
                elif a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(sub)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name in modules and a.asname:
                    mods[a.asname] = a.name
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in mods and node.attr.startswith("_")
                and not node.attr.startswith("__")):
            out.append(f"{mods[node.value.id]}.{node.attr}")
    return out


def test_no_module_reaches_into_another_modules_private_names():
    # a name another module needs is part of its module's interface: named without
    # the underscore, where a reader looks for what the module offers
    modules = _modules()
    found = {str(p.relative_to(ROOT)): names for p in PACKAGE.rglob("*.py")
             if (names := _private_imports(p, modules))}
    assert found == {}


def test_the_private_name_check_finds_both_kinds(tmp_path):
    modules = _modules()
    f = tmp_path / "m.py"
    f.write_text("from dempipe.usd.authoring import SDF_TYPES, _hidden\n"
                 "from dempipe.sim import physics as ph\n"
                 "x = ph._secret(1)\n")
    assert _private_imports(f, modules) == ["dempipe.usd.authoring._hidden",
                                            "dempipe.sim.physics._secret"]


def test_front_door_names_resolve_without_importing_pxr_or_cuda():
    code = ("import sys, dempipe\n"
            "heavy = [m for m in ('pxr', 'numba.cuda') if m in sys.modules]\n"
            "assert heavy == [], heavy\n"
            "missing = [n for n in dempipe.__all__ if not hasattr(dempipe, n)]\n"
            "assert missing == [], missing\n"
            "assert callable(dempipe.bake) and dempipe.bake.__module__ == 'dempipe.pipeline.bake'\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
