"""The package layout holds: ``service -> workers -> pipelines``, the method free of execution and storage.

The import graph is read from the source (``ast``), function-level and ``TYPE_CHECKING`` imports included, so a
cycle cannot hide in a function body.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipelines", "workers", "service")
#: What the method must not import: execution, storage and the web (ARCHITECTURE).
FORBIDDEN_IN_PIPELINES = {"dask", "distributed", "zarr", "fastapi", "subprocess", "multiprocessing"}
MAX_LINES = 600


def modules(package: str) -> dict[str, Path]:
    out = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def imports_of(name: str, path: Path) -> set[str]:
    """Every module ``path`` imports, anywhere in it, as absolute names."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)  # `from pkg import module`
    return found


def graph(package: str) -> dict[str, set[str]]:
    mods = modules(package)
    return {m: {i for i in imports_of(m, p) if i in mods and i != m} for m, p in mods.items()}


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(g[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (c := visit(n)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(g):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_pipelines_has_no_import_cycle():
    assert find_cycle(graph("pipelines")) is None


def test_no_package_has_an_import_cycle():
    g: dict[str, set[str]] = {}
    for package in PACKAGES:
        mods = modules(package)
        for m, p in mods.items():
            g[m] = imports_of(m, p)
    everything = set(g)
    assert find_cycle({m: {i for i in deps if i in everything and i != m} for m, deps in g.items()}) is None


def test_pipelines_imports_no_execution_storage_or_web_library():
    bad = {}
    for m, p in modules("pipelines").items():
        roots = {i.split(".")[0] for i in imports_of(m, p)}
        if roots & (FORBIDDEN_IN_PIPELINES | {"workers", "service"}):
            bad[m] = sorted(roots & (FORBIDDEN_IN_PIPELINES | {"workers", "service"}))
    assert not bad, bad


def test_workers_do_not_import_the_service():
    bad = [m for m, p in modules("workers").items()
           if any(i.split(".")[0] in ("service", "fastapi") for i in imports_of(m, p))]
    assert not bad, bad


def test_no_module_is_over_600_lines():
    long = {str(p.relative_to(ROOT)): n for package in PACKAGES for p in modules(package).values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_the_readme_fits_on_a_screen():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 250
