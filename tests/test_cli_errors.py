"""Issue 23, defect 8 ("CLI rough edges"): every failure of ``compabs`` is one ``error:`` line and exit 2.

Hostile spec files (binary, latin-1, a 5000-digit integer, ``/dev/zero``, a FIFO), arguments (``--set`` of an
unknown parameter, ``--audit-transitions -5``), a spec wrong in a way only the run found (``initial_states`` of
the wrong dimension), a read-only or foreign output directory, a damaged relation chunk, and a black box's NaN
on the cluster: each ends in one ``error:`` line, exit status 2, no traceback, no half-written directory, and
never another spec's results overwritten. ``compabs validate`` runs the checks that need no black-box
evaluation (:mod:`pipelines.spec.validate`), and ``compabs run`` runs them before it creates anything.
"""

from __future__ import annotations

import errno
import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipelines.errors import SpecError
from pipelines.spec.model import load_spec, spec_hash
from pipelines.spec.validate import validate_spec
from service.cli import main

from .conftest import EXAMPLES, ROOT
from .trust_log import record

#: Options that keep an in-process run of small.yaml to a few seconds.
QUICK = {"closed_loop_runs": 2, "audit_transitions": 2_000}


def spec_file(directory: Path, name: str = "spec.yaml", mutate=None, **options) -> Path:
    """small.yaml with ``options`` (and ``mutate(data)``) applied, written to ``directory / name``."""
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"] = {**data.get("options", {}), **QUICK, **options}
    if mutate is not None:
        mutate(data)
    path = directory / name
    path.write_text(yaml.safe_dump(data))
    return path


def run_cli(capsys, *args: str) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_error(code: int, err: str, *fragments: str) -> None:
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], (f, err)


def _limit_memory() -> None:  # pragma: no cover - runs in the child
    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))


def cli_process(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``compabs ARGS`` in a child process (bounded memory: the old reading of /dev/zero grew without end)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    env.pop("COMPABS_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "service.cli", *map(str, args)], cwd=ROOT, env=env, text=True,
                          capture_output=True, timeout=timeout, preexec_fn=_limit_memory)


# ============================================================================================ compabs validate
@pytest.mark.parametrize("name", ["small", "consensus", "tanks", "scalability", "stress"])
def test_validate_passes_the_examples(capsys, monkeypatch, name):
    import pipelines.abstraction.cells as cells

    def no_evaluation(*a, **k):  # the per-cell stage: validation never runs it
        raise AssertionError("validate evaluated the black boxes")

    monkeypatch.setattr(cells, "abstract_cells", no_evaluation)
    code, out, err = run_cli(capsys, "validate", EXAMPLES / f"{name}.yaml")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[-1] == "ok"
    assert lines[0].startswith("spec: ") and any(line.startswith("network: ") for line in lines)
    assert any(line.startswith("options.initial_states: ") for line in lines)
    assert any(line.startswith("caps: ") for line in lines)


def test_validate_with_set(capsys):
    code, out, _ = run_cli(capsys, "validate", EXAMPLES / "scalability.yaml", "--set", "N=8")
    assert code == 0 and "parameters: N = 8" in out


def test_validate_returns_what_it_built():
    spec = load_spec(EXAMPLES / "small.yaml")
    result = validate_spec(spec, allowed_modules=None)
    assert result.network.state_dim == 2 and set(result.regions) == {"target"}
    assert result.lines[0] == "spec: 'small' parses"


@pytest.mark.parametrize("command", ["validate", "run"])
def test_set_of_an_unknown_parameter_is_refused(tmp_path, capsys, command):
    extra = ["--out", tmp_path / "out", "--in-process", "--quiet"] if command == "run" else []
    code, _, err = run_cli(capsys, command, EXAMPLES / "small.yaml", "--set", "M=3", *extra)
    assert_one_error(code, err, "'M'", "its parameters: N")
    assert not (tmp_path / "out").exists()


def test_load_spec_refuses_unknown_overrides():
    with pytest.raises(SpecError, match="no such parameter"):
        load_spec(EXAMPLES / "small.yaml", {"N": 3, "M": 3})
    assert load_spec(EXAMPLES / "small.yaml", {"N": 3}).parameters["N"] == 3


@pytest.mark.parametrize("value", ["inf", "nan", "1e999"])
def test_set_of_a_non_finite_value_is_refused(capsys, value):
    code, _, err = run_cli(capsys, "validate", EXAMPLES / "small.yaml", "--set", f"N={value}")
    assert_one_error(code, err, "not a finite number")


def _three_components(data):
    data["options"]["initial_states"] = [[12.3, 16.2], [1, 2, 3]]


def test_initial_states_of_the_wrong_dimension_fail_validation(tmp_path, capsys):
    spec = spec_file(tmp_path, mutate=_three_components)
    code, _, err = run_cli(capsys, "validate", spec)
    assert_one_error(code, err, "options.initial_states[1] has 3 components; the system has 2 states")


def test_run_validates_before_creating_the_directory_or_a_cluster(tmp_path, capsys, monkeypatch):
    """The 3-component initial state was found only after synthesis, with a half-written directory left."""
    import workers.cluster

    def no_cluster(*a, **k):
        raise AssertionError("a cluster was started for an invalid spec")

    monkeypatch.setattr(workers.cluster, "connect", no_cluster)
    spec = spec_file(tmp_path, mutate=_three_components)
    out = tmp_path / "new" / "out"
    code, _, err = run_cli(capsys, "run", spec, "--out", out, "--quiet")
    assert_one_error(code, err, "options.initial_states[1] has 3 components; the system has 2 states")
    assert not (tmp_path / "new").exists()


def _costly(data):
    data["subsystems"][0]["lipschitz"] = {"x": "estimate", "w": 0.16, "batches": 1000, "pairs": 1_000_000}


@pytest.mark.parametrize("command", ["validate", "run"])
def test_a_knob_over_its_cap_is_refused_before_anything_starts(tmp_path, capsys, command):
    """The cost model's caps (pipelines.spec.costs) are part of the validation ``run`` does first."""
    extra = ["--out", tmp_path / "out", "--quiet"] if command == "run" else []
    code, _, err = run_cli(capsys, command, spec_file(tmp_path, mutate=_costly), *extra)
    assert_one_error(code, err, "subsystems[0].lipschitz.batches", "max_lipschitz_pairs")
    assert not (tmp_path / "out").exists()


def test_caps_of_the_command_line_follow_the_environment(tmp_path, capsys, monkeypatch):
    """The cost model's message names ``COMPABS_MAX_LIPSCHITZ_PAIRS``; setting it raises the command line's cap."""
    spec = spec_file(tmp_path, mutate=_costly)
    monkeypatch.setenv("COMPABS_MAX_LIPSCHITZ_PAIRS", "10_000_000_000")
    code, out, err = run_cli(capsys, "validate", spec)
    assert code == 0 and out.splitlines()[-1] == "ok", err
    for bad in ("lots", "0"):
        monkeypatch.setenv("COMPABS_MAX_LIPSCHITZ_PAIRS", bad)
        code, _, err = run_cli(capsys, "validate", spec)
        assert_one_error(code, err, "COMPABS_MAX_LIPSCHITZ_PAIRS")  # a cap is a positive integer


# ============================================================================================ hostile spec files
def _binary(d: Path) -> Path:
    p = d / "binary.yaml"
    p.write_bytes(bytes(range(256)) * 8)
    return p


def _latin1(d: Path) -> Path:
    p = d / "latin1.yaml"
    p.write_bytes("name: café\ndescription: Größe\n".encode("latin-1"))
    return p


def _nul(d: Path) -> Path:
    p = d / "nul.yaml"
    p.write_bytes(b"name: x\x00\n")
    return p


def _big_int(d: Path) -> Path:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    text = yaml.safe_dump(data).replace("N: 2", "N: " + "9" * 5000)
    p = d / "bigint.yaml"
    p.write_text(text)
    return p


def _big_int_json(d: Path) -> Path:
    p = d / "bigint.json"
    p.write_text('{"name": "x", "options": {"seed": ' + "7" * 5000 + "}}")
    return p


def _too_large(d: Path) -> Path:
    p = d / "large.yaml"
    p.write_text("# " + "x" * (2 << 20) + "\n")
    return p


def _directory(d: Path) -> Path:
    p = d / "adir.yaml"
    p.mkdir()
    return p


HOSTILE_FILES = [
    ("binary", _binary, "not UTF-8 text"),
    ("latin-1", _latin1, "not UTF-8 text"),
    ("NUL bytes", _nul, "binary file"),
    ("5000-digit integer (YAML)", _big_int, "digits"),
    ("5000-digit integer (JSON)", _big_int_json, "digits"),
    ("larger than 1 MiB", _too_large, "larger than"),
    ("a directory", _directory, "a directory"),
]


def test_hostile_spec_files(tmp_path, capsys):
    """A binary or latin-1 spec and a 5000-digit integer ended in a traceback; each is one error: line now."""
    tried = 0
    for label, make, match in HOSTILE_FILES:
        for command in ("run", "validate"):
            d = tmp_path / f"{tried}"
            d.mkdir()
            extra = ["--out", d / "out", "--quiet"] if command == "run" else []
            code, _, err = run_cli(capsys, command, make(d), *extra)
            assert_one_error(code, err, match)
            assert not (d / "out").exists(), label
            tried += 1
    record("CLI: hostile spec files", inputs=tried, failed_cleanly=tried)


@pytest.mark.timeout(300)
def test_device_and_fifo_specs_are_refused_without_reading(tmp_path):
    """/dev/zero was read until MemoryError; a FIFO blocked forever (no writer). Both are refused at once."""
    fifo = tmp_path / "spec.fifo"
    os.mkfifo(fifo)
    for path, match in [("/dev/zero", "a character device"), (fifo, "a FIFO")]:
        try:
            proc = cli_process("run", path, "--out", tmp_path / "out", "--quiet", timeout=120)
        except subprocess.TimeoutExpired:
            pytest.fail(f"compabs run {path} did not return (it waits on the file)")
        assert_one_error(proc.returncode, proc.stderr, match)
        assert not (tmp_path / "out").exists()
    record("CLI: device and FIFO as the spec", inputs=2, failed_cleanly=2)


# ============================================================================================ arguments
@pytest.mark.parametrize("args,match", [
    (["--audit-transitions", "-5"], "--audit-transitions"),
    (["--audit-transitions", "lots"], "not an integer"),
    (["--audit-transitions", "100000001"], "options.audit_transitions"),
    (["--workers", "0"], "--workers"),
], ids=["negative audit", "audit not a number", "audit over the bound", "no workers"])
def test_bad_arguments_are_one_error_line(tmp_path, capsys, args, match):
    """``--audit-transitions -5`` exited 0 having checked nothing."""
    code, _, err = run_cli(capsys, "run", EXAMPLES / "small.yaml", "--out", tmp_path / "out", "--quiet", *args)
    assert_one_error(code, err, match)
    assert not (tmp_path / "out").exists()


def test_usage_errors_are_one_line(capsys):
    for args in (["run"], ["nonsense"], ["audit"], ["simulate", "x", "--x0", "1", "--steps", "-1"]):
        code, _, err = run_cli(capsys, *args)
        assert_one_error(code, err)
    assert run_cli(capsys, "--help")[0] == 0


def test_audit_transitions_zero_means_no_audit(tmp_path, capsys):
    code, _, err = run_cli(capsys, "run", spec_file(tmp_path), "--out", tmp_path / "out", "--quiet", "--in-process",
                           "--no-synthesis", "--audit-transitions", "0")
    assert code == 0, err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["audit"]["transitions_checked"] == 0


# ============================================================================================ the job directory
@pytest.fixture(scope="module")
def finished_job(tmp_path_factory) -> tuple[Path, Path]:
    """(spec file, directory) of a finished in-process run of a quick small.yaml."""
    base = tmp_path_factory.mktemp("finished")
    spec = spec_file(base)
    out = base / "job"
    assert main(["run", str(spec), "--out", str(out), "--quiet", "--in-process", "--no-synthesis"]) == 0
    return spec, out


@pytest.fixture
def job(finished_job, tmp_path) -> Path:
    return Path(shutil.copytree(finished_job[1], tmp_path / "job"))


@pytest.mark.parametrize("store", ["kept", "deleted"])
def test_another_specs_directory_is_refused(job, tmp_path, capsys, store):
    """``--in-process`` into another spec's directory overwrote its report.json."""
    if store == "deleted":
        shutil.rmtree(job / "relations.zarr")
    before = (job / "report.json").read_bytes()
    other = spec_file(tmp_path, "other.yaml", seed=7)
    code, _, err = run_cli(capsys, "run", other, "--out", job, "--quiet", "--in-process", "--no-synthesis")
    assert_one_error(code, err, "another job", "--overwrite")
    assert (job / "report.json").read_bytes() == before
    record("CLI: run into another spec's directory", inputs=1, failed_cleanly=1)


def test_overwrite_replaces_another_specs_job(job, tmp_path, capsys):
    shutil.rmtree(job / "relations.zarr")
    other = spec_file(tmp_path, "other.yaml", seed=7)
    code, _, err = run_cli(capsys, "run", other, "--out", job, "--quiet", "--in-process", "--no-synthesis",
                           "--overwrite")
    assert code == 0, err
    report = json.loads((job / "report.json").read_text())
    assert report["spec_hash"] == spec_hash(load_spec(other))
    assert json.loads((job / "spec.json").read_text())["options"]["seed"] == 7


def test_the_same_spec_resumes_into_its_directory(finished_job, job, capsys):
    spec, _ = finished_job
    code, out, err = run_cli(capsys, "run", spec, "--out", job, "--quiet", "--in-process", "--no-synthesis", "--json")
    assert code == 0, err
    assert json.loads(out)["runner"]["chunks_reused"] >= 1


def test_a_failed_run_leaves_no_new_directory(tmp_path, capsys):
    """A black box's NaN in the first chunk: nothing was stored, so the new directory is removed again."""
    def nan(data):
        data["subsystems"][0]["dynamics"] = "sqrt(x[0] - 16)"

    out = tmp_path / "new" / "out"
    code, _, err = run_cli(capsys, "run", spec_file(tmp_path, mutate=nan), "--out", out, "--quiet", "--in-process")
    assert_one_error(code, err, "not finite")
    assert not (tmp_path / "new").exists()


def _refuse_writes_in(monkeypatch, directory: Path) -> None:
    """Make ``directory`` behave as read-only for files created through os.open (the tests run as root, whom a
    chmod does not stop)."""
    real_open = os.open
    inside = str(directory.resolve())

    def guarded(path, flags, *args, **kwargs):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) and os.path.abspath(os.fspath(path)).startswith(inside):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", guarded)


def test_read_only_directory_fails_at_the_start(job, finished_job, capsys, monkeypatch):
    """``--in-process`` into a read-only directory failed with a PermissionError traceback after the whole
    abstraction; it now fails before any stage, naming the directory."""
    import workers.job

    def no_stage(*a, **k):
        raise AssertionError("the abstraction ran in a directory that cannot be written")

    monkeypatch.setattr(workers.job, "run_abstraction", no_stage)
    _refuse_writes_in(monkeypatch, job)
    code, _, err = run_cli(capsys, "run", finished_job[0], "--out", job, "--quiet", "--in-process")
    assert_one_error(code, err, str(job), "cannot write")
    record("CLI: read-only output directory", faults=1, failed_cleanly=1)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into a read-only directory")
def test_read_only_directory_by_permissions(job, finished_job, capsys):
    for path in [job, *job.rglob("*")]:
        path.chmod(path.stat().st_mode & ~0o222)
    try:
        code, _, err = run_cli(capsys, "run", finished_job[0], "--out", job, "--quiet", "--in-process")
    finally:
        for path in [job, *job.rglob("*")]:
            path.chmod(path.stat().st_mode | 0o200)
    assert_one_error(code, err, str(job))


def test_damaged_chunk_is_never_a_traceback(job, finished_job, capsys):
    """Garbage bytes in a relation chunk crashed with a raw blosc RuntimeError. Whatever the store makes of it
    (recomputed, or refused), the command ends in exit 0 or one error: line."""
    chunks = sorted(p for p in (job / "relations.zarr").rglob("*") if p.is_file() and "/lo/c/" in p.as_posix())
    assert chunks, "no chunk files found"
    chunks[0].write_bytes(b"\x00garbage" * 16)
    code, _, err = run_cli(capsys, "run", finished_job[0], "--out", job, "--quiet", "--in-process", "--no-synthesis")
    assert "Traceback" not in err
    if code != 0:
        assert_one_error(code, err)
    else:  # recomputed: the same relations as the undamaged job's
        subsystems = [json.loads((d / "report.json").read_text())["subsystems"] for d in (finished_job[1], job)]
        assert [s["mean_successors"] for s in subsystems[0]] == [s["mean_successors"] for s in subsystems[1]]
    record("CLI: damaged relation chunk", faults=1, failed_cleanly=int(code == 2), identical=int(code == 0), wrong=0)


@pytest.mark.parametrize("exc", [OSError(errno.EIO, "Input/output error", "relations.zarr/x"),
                                 RuntimeError("error during blosc decompression: -1")],
                         ids=["OSError", "internal error"])
def test_store_errors_end_as_one_line(tmp_path, capsys, monkeypatch, exc):
    import workers.relation_store

    def broken(*a, **k):
        raise exc

    monkeypatch.setattr(workers.relation_store.RelationStore, "open", broken)
    (tmp_path / "existing").mkdir()
    out = tmp_path / "existing" / "a" / "b"
    code, _, err = run_cli(capsys, "run", spec_file(tmp_path), "--out", out, "--quiet", "--in-process")
    assert_one_error(code, err, str(exc.args[-1]) if isinstance(exc, RuntimeError) else "Input/output error")
    assert list((tmp_path / "existing").iterdir()) == []


# ============================================================================================ the cluster
@pytest.mark.timeout(300)
def test_black_box_nan_on_the_cluster_prints_no_worker_traceback(tmp_path):
    """A black box's NaN printed Dask's "Compute Failed" record and the worker's traceback before the clean
    error line, even with --quiet."""
    def nan(data):
        data["subsystems"][0]["dynamics"] = "sqrt(x[0] - 16)"

    spec = spec_file(tmp_path, mutate=nan)
    for quiet in (["--quiet"], []):
        proc = cli_process("run", spec, "--out", tmp_path / "out", "--workers", "1", *quiet, timeout=240)
        assert "Compute Failed" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
        assert proc.returncode == 2, proc.stderr
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and "not finite" in errors[0], proc.stderr
        assert proc.stderr.strip().splitlines()[-1] == errors[0]
        assert not (tmp_path / "out" / "report.json").exists()
    record("CLI: black box NaN on the cluster", faults=2, failed_cleanly=2)


def test_credentials_refuses_bad_input_with_one_error_line(tmp_path, capsys):
    """``compabs credentials DIR``: a DIR that is a file, or a non-positive validity, is one ``error:`` line."""
    a_file = tmp_path / "a_file"
    a_file.write_text("not a directory")
    assert_one_error(*run_cli(capsys, "credentials", a_file)[::2], "a_file")
    assert_one_error(*run_cli(capsys, "credentials", tmp_path / "tls", "--days", "-3")[::2], "--days")
    assert not (tmp_path / "tls").exists()
