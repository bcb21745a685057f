"""The lock file the Docker image installs from (``requirements.lock``) is in sync with pyproject.toml, and the
image is reproducible: its base pinned by digest, its packages installed from the lock with hashes.

After a change of ``[project].dependencies``, regenerate the lock with the command at its top (uv, Python 3.11,
linux x86_64, hashes).
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


def _dependencies(pyproject: dict) -> list[Requirement]:
    reqs = [Requirement(d) for d in pyproject["project"]["dependencies"]]
    return [r for r in reqs if r.marker is None or r.marker.evaluate(TARGET)]


def test_every_dependency_is_pinned_in_the_lock_within_its_specifier(lock, pyproject):
    for req in _dependencies(pyproject):
        name = canonicalize_name(req.name)
        assert name in lock, f"{req} of pyproject.toml is not in requirements.lock: regenerate it"
        version = Version(lock[name]["version"])
        assert req.specifier.contains(version, prereleases=True), (
            f"requirements.lock pins {name}=={version}, outside pyproject.toml's {req}: regenerate it")


def test_the_lock_pins_no_top_level_package_pyproject_lacks(lock, pyproject):
    """A dependency dropped from pyproject.toml leaves the lock too (uv marks top-level pins ``via compabs``)."""
    declared = {canonicalize_name(r.name) for r in _dependencies(pyproject)}
    top_level = {name for name, pin in lock.items() if any(v.startswith("compabs") for v in pin["via"])}
    assert top_level == declared, (sorted(top_level - declared), sorted(declared - top_level))
    orphans = [name for name, pin in lock.items() if not pin["via"]]
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
