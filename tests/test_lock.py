"""The lock files are in sync with pyproject.toml: ``requirements.lock`` (the Docker image installs it) pins
``[project].dependencies``, ``requirements-test.lock`` (CI, ``.ci/run``, installs it) pins those and the ``test``
extra at the same versions; both with hashes. The image is reproducible: its base pinned by digest, its packages
installed from the lock with hashes.

After a change of the dependencies, regenerate both with the commands at their tops (uv, Python 3.11, linux
x86_64, hashes; the test lock constrained by the runtime lock), the runtime lock first.
"""

from __future__ import annotations

import re

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

from .conftest import ROOT

tomllib = pytest.importorskip("tomllib")

LOCK = ROOT / "requirements.lock"
TEST_LOCK = ROOT / "requirements-test.lock"
#: The environment the lock is for (the image's): markers of pyproject's dependencies are evaluated in it.
TARGET = {"python_version": "3.11", "python_full_version": "3.11.13", "sys_platform": "linux",
          "platform_system": "Linux", "platform_machine": "x86_64", "os_name": "posix",
          "implementation_name": "cpython", "platform_python_implementation": "CPython"}


def parse_lock(text: str) -> dict[str, dict]:
    """``{name: {"version", "hashes", "via"}}`` of a ``uv pip compile``/pip-compile lock (names canonical)."""
    out: dict[str, dict] = {}
    current: dict | None = None
    in_via = False
    for line in text.splitlines():
        pin = re.match(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s\\;]+)", line)
        if pin:
            current = out[canonicalize_name(pin[1])] = {"version": pin[2], "hashes": [], "via": set()}
            in_via = False
            continue
        if current is None:
            continue
        stripped = line.strip()
        current["hashes"] += re.findall(r"--hash=sha256:([0-9a-f]{64})", stripped)
        via = re.match(r"^#\s+via\s*(.*)$", stripped)
        if via:
            in_via = True
            if via[1]:
                current["via"].add(via[1].strip())
        elif in_via and stripped.startswith("#") and stripped.lstrip("#").strip():
            current["via"].add(stripped.lstrip("#").strip())
        elif not stripped.startswith("#"):
            in_via = False
    return out


@pytest.fixture(scope="module")
def lock() -> dict[str, dict]:
    return parse_lock(LOCK.read_text())


@pytest.fixture(scope="module")
def pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


@pytest.fixture(scope="module")
def test_lock() -> dict[str, dict]:
    return parse_lock(TEST_LOCK.read_text())


def _dependencies(pyproject: dict, extra: bool = False) -> list[Requirement]:
    specs = pyproject["project"]["dependencies"] + (pyproject["project"]["optional-dependencies"]["test"]
                                                    if extra else [])
    reqs = [Requirement(d) for d in specs]
    return [r for r in reqs if r.marker is None or r.marker.evaluate(TARGET)]


@pytest.mark.parametrize("extra", [False, True], ids=["runtime", "test"])
def test_each_lock_pins_every_dependency_within_its_specifier(lock, test_lock, pyproject, extra):
    pins = test_lock if extra else lock
    for req in _dependencies(pyproject, extra):
        name = canonicalize_name(req.name)
        assert name in pins, f"{req} of pyproject.toml is not in the lock: regenerate it"
        version = Version(pins[name]["version"])
        assert req.specifier.contains(version, prereleases=True), (
            f"the lock pins {name}=={version}, outside pyproject.toml's {req}: regenerate it")
    assert all(pin["hashes"] for pin in pins.values()), [n for n, p in pins.items() if not p["hashes"]]


def test_ci_tests_the_versions_the_image_runs(lock, test_lock):
    """Every package of the image's lock is in the test lock at the same version (CI tests what ships)."""
    assert set(lock) <= set(test_lock), sorted(set(lock) - set(test_lock))
    differ = {n: (lock[n]["version"], test_lock[n]["version"]) for n in lock
              if lock[n]["version"] != test_lock[n]["version"]}
    assert not differ, f"requirements-test.lock differs from requirements.lock (regenerate it): {differ}"


def test_ci_installs_from_the_test_lock():
    text = (ROOT / ".ci" / "run").read_text()
    assert re.search(r"pip install [^\n]*--require-hashes -r requirements-test\.lock", text)
    installs = re.findall(r"pip install ([^\n]*)", text)
    # nothing resolved outside the lock: every other install is pip itself or compabs without its dependencies
    assert all("--require-hashes" in i or "--no-deps" in i or i.strip().endswith("pip") for i in installs), installs


@pytest.mark.parametrize("extra", [False, True], ids=["runtime", "test"])
def test_the_lock_pins_no_top_level_package_pyproject_lacks(lock, test_lock, pyproject, extra):
    """A dependency dropped from pyproject.toml leaves the lock too (uv marks top-level pins ``via compabs``)."""
    pins = test_lock if extra else lock
    declared = {canonicalize_name(r.name) for r in _dependencies(pyproject, extra)}
    top_level = {name for name, pin in pins.items() if any(v.startswith("compabs") for v in pin["via"])}
    assert top_level == declared, (sorted(top_level - declared), sorted(declared - top_level))
    orphans = [name for name, pin in pins.items() if not pin["via"]]
    assert not orphans, f"pins nothing requires: {orphans}"


def test_every_pin_has_a_hash_and_the_build_backend_is_pinned(lock, pyproject):
    assert len(lock) > len(pyproject["project"]["dependencies"])  # the transitive ones too
    assert all(pin["hashes"] for pin in lock.values()), [n for n, p in lock.items() if not p["hashes"]]
    # The image builds compabs without build isolation, with the lock's setuptools: it must satisfy build-system.
    for spec in pyproject["build-system"]["requires"]:
        req = Requirement(spec)
        assert req.specifier.contains(Version(lock[canonicalize_name(req.name)]["version"]))


def test_parse_lock_reads_uv_and_pip_compile_blocks():
    text = ("# header\nfoo==1.2 \\\n    --hash=sha256:" + "a" * 64 + "\n    # via compabs (pyproject.toml)\n"
            "Bar_Baz==2.0 \\\n    --hash=sha256:" + "b" * 64 + " \\\n    --hash=sha256:" + "c" * 64 + "\n"
            "    # via\n    #   foo\n    #   compabs (pyproject.toml)\n")
    got = parse_lock(text)
    assert got["foo"] == {"version": "1.2", "hashes": ["a" * 64], "via": {"compabs (pyproject.toml)"}}
    assert got["bar-baz"]["hashes"] == ["b" * 64, "c" * 64] and got["bar-baz"]["via"] == {"foo", "compabs (pyproject.toml)"}


def test_the_image_is_pinned_and_installs_from_the_lock():
    text = (ROOT / "Dockerfile").read_text()
    froms = re.findall(r"^FROM\s+(\S+)", text, re.M)
    assert froms and all(re.search(r"@sha256:[0-9a-f]{64}$", f) for f in froms), froms
    assert "COPY requirements.lock" in text
    assert re.search(r"pip install --require-hashes -r requirements\.lock", text)
    # compabs itself adds nothing unpinned: no dependency resolution, the lock's setuptools as build backend.
    installs = re.findall(r"pip install ([^&\n]*)", text)
    assert all("--require-hashes" in i or "--no-deps" in i for i in installs), installs
    assert any("--no-build-isolation" in i for i in installs if "--no-deps" in i), installs
