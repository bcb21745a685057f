"""The ``compabs`` command: bad input fails with a specific message and a non-zero exit."""

import json
import subprocess
import sys

import pytest
import yaml

from service.cli import main

from .conftest import EXAMPLES


def _write(tmp_path, mutate):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    mutate(data)
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _set(path, value):
    def mutate(d):
        for k in path[:-1]:
            d = d[k]
        d[path[-1]] = value
    return mutate


BAD = [
    ("expression outside the whitelist", _set(("subsystems", 0, "dynamics"), "__import__('os').system('true')"), "__import__"),
    ("attribute access", _set(("interconnection", "map"), "x.__class__"), "__class__"),
    ("black box returns NaN", _set(("subsystems", 0, "dynamics"), "sqrt(x[0] - 16)"), "not finite"),
    ("black box returns inf", _set(("subsystems", 0, "dynamics"), "1 / (x[0] - x[0])"), "not finite"),
    ("contradicted Lipschitz constant", _set(("subsystems", 0, "lipschitz"), {"x": 1.599, "w": 1.599}), "contradicted by the data"),
    ("empty state box", _set(("subsystems", 0, "state"), {"lb": 5, "ub": 1, "eta": 1}), "empty box"),
    ("empty input grid", _set(("subsystems", 0, "input"), {"lb": 0.2, "ub": 0.4, "eta": 1}), "empty grid"),
    ("empty region", _set(("specification", "target"), {"boxes": [{"lb": 0.6, "ub": 1.4}]}), "no whole grid cell"),
    ("sigma < 1", _set(("interconnection", "sigma"), 0), "interconnection.sigma"),
    ("wrong type", _set(("subsystems", 0, "samples"), "lots"), "subsystems.0.samples"),
]


@pytest.mark.parametrize("label,mutate,match", BAD, ids=[b[0] for b in BAD])
def test_bad_input_fails_with_a_specific_message(tmp_path, capsys, label, mutate, match):
    spec = _write(tmp_path, mutate)
    code = main(["run", str(spec), "--out", str(tmp_path / "out"), "--quiet", "--in-process"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("error: ")
    assert match in err
    assert "Traceback" not in err


#: The cases of BAD that need no black-box evaluation: ``compabs validate`` finds them.
STATIC = {"expression outside the whitelist", "attribute access", "empty state box", "empty input grid", "empty region",
          "sigma < 1", "wrong type"}


@pytest.mark.parametrize("label,mutate,match", [b for b in BAD if b[0] in STATIC], ids=sorted(STATIC, key=[b[0] for b in BAD].index))
def test_validate_finds_what_needs_no_evaluation(tmp_path, capsys, label, mutate, match):
    code = main(["validate", str(_write(tmp_path, mutate))])
    out, err = capsys.readouterr()
    assert code == 2, out
    assert err.startswith("error: ") and match in err and len(err.strip().splitlines()) == 1
    assert "ok" not in out.splitlines()


def test_missing_spec_file(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "cannot read spec" in capsys.readouterr().err


def test_bad_set_override(tmp_path, capsys):
    code = main(["run", str(EXAMPLES / "small.yaml"), "--out", str(tmp_path), "--set", "N=two", "--quiet"])
    assert code == 2 and "not a number" in capsys.readouterr().err


def test_schema_command(capsys):
    assert main(["schema"]) == 0
    assert json.loads(capsys.readouterr().out)["title"] == "JobSpec"


@pytest.mark.parametrize("argv", [["--version"], ["schema"], ["validate", str(EXAMPLES / "dcdc.yaml")]])
def test_quick_commands_import_no_plotting_or_bdds(argv):
    """``--version``, ``schema`` and ``validate`` answer in well under a second because they import neither
    matplotlib nor CUDD (asserted on what is imported, not on a time)."""
    code = ("import sys; from service.cli import main; status = main(sys.argv[1:]); "
            "heavy = sorted({m.split('.')[0] for m in sys.modules} & {'matplotlib', 'dd', 'distributed', 'zarr'}); "
            "print('HEAVY', heavy); sys.exit(status)")
    out = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "HEAVY []" in out.stdout
