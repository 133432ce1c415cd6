"""Every schema is a valid JSON Schema, round-trips through a real HDF5 file, and rejects bad input."""

import numpy as np
import pytest

import data_schemas
from helpers import REPO
from pipeline.base.store import StoreError, read_record, write_record
from schema_examples import example_record

STAGES = data_schemas.stage_schema_names()


def test_all_five_stage_outputs_have_schemas():
    assert {"calibration", "illumination", "capture", "normals", "depth"} <= set(STAGES)


@pytest.mark.parametrize("name", STAGES)
def test_stage_schema_round_trip(tmp_path, name):
    rec = example_record(name)
    path = write_record(tmp_path / f"{name}.h5", rec)
    back = read_record(path, schema=name)
    assert set(back.data) == set(rec.data)
    for k, v in rec.data.items():
        assert back.data[k].dtype == v.dtype or (v.dtype.kind == "U" and back.data[k].dtype.kind == "U")
        np.testing.assert_array_equal(back.data[k], v)
    assert back.meta == rec.meta
    assert back.provenance["iristac_schema"] == name
    assert back.provenance["iristac_schema_version"] == data_schemas.schema_version(name)


@pytest.mark.parametrize("name", STAGES)
def test_stage_schema_requires_its_datasets(tmp_path, name):
    rec = example_record(name, all_datasets=False)
    required = data_schemas.stage_schema(name)["properties"]["datasets"]["required"]
    del rec.data[required[0]]
    with pytest.raises(StoreError, match=required[0]):
        write_record(tmp_path / "x.h5", rec)
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("name", data_schemas.config_schema_names())
def test_config_schemas_are_valid_json_schemas(name):
    import jsonschema

    jsonschema.Draft202012Validator.check_schema(data_schemas.config_schema(name))


def test_dims_must_agree_across_datasets(tmp_path):
    rec = example_record("normals")
    rec.data["mask"] = np.ones((2, 4, 6), bool)  # W=6 but normals say W=5
    with pytest.raises(StoreError, match=r"'mask' has W=6 .* 'normals' has W=5"):
        write_record(tmp_path / "n.h5", rec)


def test_wrong_dtype_and_rank_named(tmp_path):
    rec = example_record("depth")
    rec.data["height"] = rec.data["height"].astype(np.int32)
    with pytest.raises(StoreError, match="height"):
        write_record(tmp_path / "d.h5", rec)
    rec = example_record("depth")
    rec.data["height"] = rec.data["height"][0]
    with pytest.raises(StoreError, match="height"):
        write_record(tmp_path / "d.h5", rec)


def test_missing_required_attribute_named(tmp_path):
    rec = example_record("capture")
    del rec.meta["mm_per_px"]
    with pytest.raises(StoreError, match="mm_per_px"):
        write_record(tmp_path / "c.h5", rec)


def test_config_unknown_key_names_key_and_allowed_keys():
    with pytest.raises(data_schemas.SchemaError) as e:
        data_schemas.validate_config("pipeline", {"normals": {"solvr": "lstsq"}}, "run.yaml")
    msg = str(e.value)
    assert "run.yaml" in msg and "'solvr'" in msg and "solver" in msg and "ratio" in msg


def test_config_wrong_type_names_field():
    with pytest.raises(data_schemas.SchemaError, match=r"run.yaml: depth/integrator"):
        data_schemas.validate_config("pipeline", {"depth": {"integrator": 3}}, "run.yaml")


def test_config_choices_come_from_the_registries():
    """``x-choices`` nodes take their ``enum`` from the registries the caller passes."""
    from pipeline.stages.config import config_choices

    cfg = {"depth": {"integrator": "magic"}}
    data_schemas.validate_config("pipeline", cfg, "run.yaml")  # no registries: only the type is checked
    with pytest.raises(data_schemas.SchemaError, match=r"run.yaml: depth/integrator.*'fc', 'dct', 'dst', 'sparse'"):
        data_schemas.validate_config("pipeline", cfg, "run.yaml", choices=config_choices())


def test_load_config_file_reports_bad_yaml(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("cache: [unclosed\n")
    with pytest.raises(data_schemas.SchemaError, match="bad.yaml: not valid YAML"):
        data_schemas.load_config_file("pipeline", p)
    p.write_text("cache: c\nnormalz: {}\n")
    with pytest.raises(data_schemas.SchemaError, match="unknown key 'normalz'"):
        data_schemas.load_config_file("pipeline", p)


def test_a_config_file_that_is_not_utf8_is_one_clear_error_everywhere(tmp_path):
    """Latin-1 bytes in a sensor profile, a user mode, a pipeline config or a scene file: an error naming
    the file, never a traceback."""
    from pipeline.base.errors import UserError
    from pipeline.base.modes import load_mode
    from pipeline.capture.sensor_profiles import load_profile
    from pipeline.workflows.run import load_pipeline_config
    from sim.scene import load_scene

    p = tmp_path / "caf\u00e9.yaml"
    p.write_bytes("name: caf\u00e9\n".encode("latin-1"))
    with pytest.raises(data_schemas.SchemaError, match="caf\u00e9.yaml: not valid YAML"):
        data_schemas.load_config_file("sensor", p)
    for load in (load_profile, load_mode, load_pipeline_config, load_scene):
        with pytest.raises(UserError, match="caf\u00e9.yaml: not valid YAML"):
            load(p)


@pytest.mark.parametrize("name", sorted(str(p.relative_to(REPO)) for d in ("pipeline", "sim", "calibration",
                                                                           "data_schemas", "examples")
                                        for p in (REPO / d).rglob("*.yaml")))
def test_the_one_yaml_reader_reads_every_shipped_file_as_pyyaml_safe_load_does(name):
    """safe_load_yaml (libyaml's parser when present) gives the very objects of the pure-Python
    yaml.safe_load on every YAML file the project ships (modes, sensor profiles, scenes, examples)."""
    import yaml

    from data_schemas import safe_load_yaml

    text = (REPO / name).read_text(encoding="utf-8")
    assert safe_load_yaml(text) == yaml.load(text, Loader=yaml.SafeLoader)


def test_the_one_yaml_reader_refuses_what_safe_load_refuses():
    import yaml

    from data_schemas import safe_load_yaml

    for bad in ("a: [1, 2", "!!python/object/apply:os.system ['true']", "a: b: c"):
        with pytest.raises(yaml.YAMLError):
            safe_load_yaml(bad)
