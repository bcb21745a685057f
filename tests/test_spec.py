"""Job specs: the examples load; malformed specs get a message naming the field."""

import copy

import pytest
import yaml

from pipelines.errors import SpecError
from pipelines.network import build_network
from pipelines.spec.model import json_schema, load_spec, parse_spec

from .conftest import EXAMPLES


@pytest.mark.parametrize("name", ["small", "consensus", "tanks", "scalability"])
def test_examples_load(name):
    spec = load_spec(EXAMPLES / f"{name}.yaml")
    assert build_network(spec, None).subsystems


def test_parameters_set_the_network_size():
    for n in (4, 8, 16, 32):
        spec = load_spec(EXAMPLES / "scalability.yaml", {"N": n})
        assert len(build_network(spec, None).subsystems) == n


def test_identical_subsystems_are_grouped():
    net = build_network(load_spec(EXAMPLES / "tanks.yaml"), None)
    sizes = sorted(len(g) for g in net.unique_subsystems().values())
    assert sizes == [2, 8]  # the two tap-fed tanks, the eight others


def _small():
    return yaml.safe_load((EXAMPLES / "small.yaml").read_text())


@pytest.mark.parametrize(
    "path,value,field",
    [
        (("interconnection", "sigma"), 0, "interconnection.sigma"),
        (("interconnection", "sigma"), "four", "interconnection.sigma"),
        (("subsystems", 0, "samples"), "many", "subsystems.0.samples"),
        (("subsystems", 0, "state", "eta"), "wide", "subsystems.0.state.eta"),
        (("subsystems", 0, "growth_bound"), "magic", "subsystems.0.growth_bound"),
        (("subsystems", 0, "lipschitz", "x"), -1.0, "subsystems.0.lipschitz.x"),
        (("specification", "kind"), "eventually", "specification.kind"),
        (("options", "seed"), "abc", "options.seed"),
    ],
)
def test_wrong_types_name_the_field(path, value, field):
    data = _small()
    d = data
    for p in path[:-1]:
        d = d[p]
    d[path[-1]] = value
    with pytest.raises(SpecError) as exc:
        parse_spec(data)
    assert field in str(exc.value)


def test_unknown_fields_are_rejected():
    data = _small()
    data["subsystems"][0]["dynamcis"] = "x[0]"
    with pytest.raises(SpecError, match="dynamcis"):
        parse_spec(data)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d["subsystems"][0].update(state={"lb": 5, "ub": 1, "eta": 1}), "empty box"),
        (lambda d: d["subsystems"][0].update(input={"lb": 0.2, "ub": 0.4, "eta": 1}), "empty grid"),
        (lambda d: d["subsystems"][0].update(reads=[3]), "internal variable 3 does not exist"),
        (lambda d: d["subsystems"][0].update(replicate="M"), "parameter 'M'"),
        (lambda d: d["subsystems"][0].update(dynamics="x[0].__class__"), "attribute"),
        (lambda d: d["interconnection"].update(map="__import__('os')"), "__import__"),
    ],
)
def test_inconsistent_specs_are_rejected(mutate, match):
    data = copy.deepcopy(_small())
    mutate(data)
    with pytest.raises(SpecError, match=match):
        build_network(parse_spec(data), None)


def test_not_a_mapping():
    with pytest.raises(SpecError, match="mapping"):
        parse_spec("- 1\n- 2\n")
    with pytest.raises(SpecError, match="YAML"):
        parse_spec("a: [1, 2")


def test_module_functions_need_the_allowlist():
    data = _small()
    data["subsystems"][0]["dynamics"] = "os.path:join"
    with pytest.raises(SpecError, match="allowlist"):
        build_network(parse_spec(data), allowed_modules=("numpy",))


def test_schema_is_json_schema():
    schema = json_schema()
    assert schema["type"] == "object"
    assert "subsystems" in schema["properties"]


def test_the_saved_controller_must_be_computed():
    data = _small()
    data["options"]["fixed_points"] = ["reach_safe"]
    with pytest.raises(SpecError, match="controller"):
        parse_spec(data)
    data["options"]["controller"] = "reach_safe"
    assert parse_spec(data).options.fixed_points == ["reach_safe"]


@pytest.mark.parametrize("centers", [[0, 1e308, 1e-308], [0, 31, 1e-9], [0, float("inf"), 1], [float("nan"), 31, 1]])
def test_consensus_centres_that_overflow_are_a_spec_error(centers):
    """Found by hypothesis through POST /jobs: a tiny step made the centre count inf (a 500 before)."""
    import yaml

    from pipelines.network import build_network
    from pipelines.spec.regions import spec_regions

    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["specification"]["target"]["consensus"]["centers"] = centers
    with pytest.raises(SpecError, match="consensus"):
        spec = parse_spec(data)
        spec_regions(spec, build_network(spec, None))


@pytest.mark.parametrize("value, ok", [("auto", True), (1, True), (4, True), (0, False), (-2, False), (65, False),
                                       ("many", False), (2.5, False)])
def test_synthesis_processes_option(value, ok):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data.setdefault("options", {})["synthesis_processes"] = value
    if ok:
        assert parse_spec(yaml.safe_dump(data)).options.synthesis_processes == value
    else:
        with pytest.raises(SpecError, match="synthesis_processes"):
            parse_spec(yaml.safe_dump(data))


def test_synthesis_processes_is_not_part_of_the_spec_hash():
    from pipelines.spec.model import spec_hash

    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    base = spec_hash(parse_spec(yaml.safe_dump(data)))
    data.setdefault("options", {})["synthesis_processes"] = 1
    assert spec_hash(parse_spec(yaml.safe_dump(data))) == base
    data["options"]["seed"] = 1
    assert spec_hash(parse_spec(yaml.safe_dump(data))) != base
