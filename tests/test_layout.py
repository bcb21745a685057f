"""The package layout holds: ``service -> workers -> pipelines``, the method free of execution and storage; ``bench/``
and ``tests/`` have no import cycle; no function of the three packages is over 100 lines, no two modules share a
name; the repository refers to no file outside itself; the prose of the three packages has no dates.

The import graph is read from the source (``ast``), function-level and ``TYPE_CHECKING`` imports included, so a
cycle cannot hide in a function body.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipelines", "workers", "service")
#: What the method must not import: execution, storage and the web (ARCHITECTURE).
FORBIDDEN_IN_PIPELINES = {"dask", "distributed", "zarr", "fastapi", "subprocess", "multiprocessing"}
MAX_LINES = 600
#: A reference to a file a user of the repository does not have (the workspace around it, the method notes that
#: docs/method.md replaces).
OUTSIDE = re.compile(r"\.\./shared|/work/shared|METHOD\.md|METHOD\s§")
#: A date: ISO (2026-11-27, 2026/11/27) or with the month's name (November 2026, 27 Nov 2026, Nov. 27, 2026).
_MONTH = (r"(?:Jan(?:uary)?|Feb(?:ruary)?|Mar(?:ch)?|Apr(?:il)?|May|June?|July?|Aug(?:ust)?|Sept?(?:ember)?"
          r"|Oct(?:ober)?|Nov(?:ember)?|Dec(?:ember)?)")
DATE = re.compile(rf"\b(?:19|20)\d\d[-/][01]\d[-/][0-3]\d\b|\b{_MONTH}\.?\s+(?:[0-3]?\d(?:st|nd|rd|th)?,?\s+)?(?:19|20)\d\d\b")


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


#: Module names more than one package may use: the package marker, and each layer's one ``errors`` module (always
#: imported with its package, ``pipelines.errors`` / ``workers.errors`` / ``service.errors``).
SHARED_NAMES = {"__init__", "errors"}


def test_no_two_modules_share_a_name():
    by_name: dict[str, list[str]] = {}
    for package in PACKAGES:
        for p in sorted((ROOT / package).rglob("*.py")):
            by_name.setdefault(p.stem, []).append(str(p.relative_to(ROOT)))
    shared = {n: ps for n, ps in by_name.items() if len(ps) > 1 and n not in SHARED_NAMES}
    assert not shared, shared


def repository_files(*suffixes: str) -> list[Path]:
    """The repository's files with these suffixes, outside hidden directories (``.git``, ``.venv``, ...) and caches."""
    return sorted(p for p in ROOT.rglob("*") if p.suffix in suffixes and p.is_file()
                  and not any(part.startswith(".") or part == "__pycache__" for part in p.relative_to(ROOT).parts))


def prose(path: Path) -> list[tuple[int, str]]:
    """The docstrings and comments of a Python file (every string that is a statement of its own: module, class,
    function and attribute docstrings), or the comments of a YAML file, as (line, text)."""
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        return [(i, line[line.index("#"):]) for i, line in enumerate(text.splitlines(), 1) if "#" in line]
    out = [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(text).readline)
           if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(text, str(path))):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            out.append((node.lineno, node.value.value))
    return out


def test_the_date_finder_finds_dates():
    for dated in ("the same domain (2026-11-28, alternating)", "measured 2026/11/27", "on 27 November 2026",
                  "in Nov 2026", "Nov. 27, 2026", "December 3rd, 2025"):
        assert DATE.search(dated), dated
    for undated in ("glibc 2.35", "N = 1024", "Meyer, Girard & Witrant 2017", "May 2x faster", "spacing 1.25",
                    "2·10^12 states", "issue 24"):
        assert not DATE.search(undated), undated


def test_tests_have_no_import_cycle():
    assert find_cycle(graph("tests")) is None


def reachable(g: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = {start}, [start]
    while todo:
        for n in g.get(todo.pop(), ()):
            if n not in seen:
                seen.add(n)
                todo.append(n)
    return seen


def test_controllers_do_not_import_their_exports():
    """The exports are built from controllers: nothing a controller imports reaches ``pipelines.export`` (the
    loader of every controller kind, ``pipelines.controller_loading``, sits above both)."""
    g = graph("pipelines")
    for start in ("pipelines.controller", "pipelines.array_controller", "pipelines.grid_controller"):
        assert not {m for m in reachable(g, start) if m.startswith("pipelines.export")}, start


#: The longest function of the three packages (lines from ``def`` to its end, docstring included).
MAX_FUNCTION_LINES = 100
#: The most parameters a job's entry points take (the rest travels in option objects).
MAX_ENTRY_PARAMETERS = 8


def functions(package: str):
    for path in sorted((ROOT / package).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                yield path, node


def test_no_function_is_over_100_lines():
    long = {f"{p.relative_to(ROOT)}::{f.name}": n for package in PACKAGES for p, f in functions(package)
            if (n := f.end_lineno - f.lineno + 1) > MAX_FUNCTION_LINES}  # type: ignore[operator]
    assert not long, long


def test_the_job_entry_points_take_at_most_8_parameters():
    entry = {"pipelines/synthesis/synthesize.py": "synthesize", "workers/job.py": ("run_job", "abstract_job")}
    counts = {}
    for package in ("pipelines", "workers"):
        for p, f in functions(package):
            names = entry.get(str(p.relative_to(ROOT)), ())
            if f.name in names:
                a = f.args
                counts[f.name] = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
    assert set(counts) == {"synthesize", "run_job", "abstract_job"}, counts
    assert max(counts.values()) <= MAX_ENTRY_PARAMETERS, counts


def test_bench_has_no_import_cycle():
    assert find_cycle(graph("bench")) is None


def test_nothing_refers_to_files_outside_the_repository():
    """A user has the repository only: no path into the shared folder beside it (``/work/shared`` or relative) or
    the method notes that docs/method.md replaces, in code, docs or configuration."""
    me = Path(__file__).resolve()  # names the patterns
    found = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
             for p in repository_files(".py", ".md", ".yaml", ".yml") if p.resolve() != me
             for i, line in enumerate(p.read_text().splitlines(), 1) if OUTSIDE.search(line)]
    assert not found, "\n".join(found)


def test_no_docstring_or_comment_carries_a_date():
    """History lives in git and the issues: the prose of the three packages says why the code is as it is, now."""
    found = [f"{p.relative_to(ROOT)}:{line}: {DATE.search(text).group()}"  # type: ignore[union-attr]
             for package in PACKAGES for p in sorted((ROOT / package).rglob("*"))
             if p.suffix in (".py", ".yaml", ".yml") and "__pycache__" not in p.parts
             for line, text in prose(p) if DATE.search(text)]
    assert not found, "\n".join(found)


def test_the_readme_and_the_benchmarks_page_stay_short():
    """The front door and the current figures, not a lab notebook: reference material and history live elsewhere
    (docs/, git, issue notes)."""
    for page in ("README.md", "docs/benchmarks.md"):
        assert len((ROOT / page).read_text().splitlines()) <= 200, page
