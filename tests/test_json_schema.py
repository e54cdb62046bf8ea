"""The JSON outputs follow their schemas (data_schema/json/) and name the
unit of every number in its key. Each command's ``--json`` is checked in its
own CLI test (tests/test_cli_*.py); here the whole pipeline's result.json,
which holds every stage's contract."""
from __future__ import annotations

import json

import pytest
from json_schemas import SCHEMAS, check_schema, keys_without_unit

jsonschema = pytest.importorskip("jsonschema")


def test_schema_files_are_valid_draft_2020_12():
    names = sorted(p.name.split(".")[0] for p in SCHEMAS.glob("*.schema.json"))
    assert names == ["common", "discover", "flowfit", "identify", "ingest", "run", "tracking",
                     "validate"]
    for path in SCHEMAS.glob("*.schema.json"):
        jsonschema.Draft202012Validator.check_schema(json.loads(path.read_text()))


def test_pipeline_result_follows_the_schema_and_names_units(golden_run):
    doc, _ = golden_run
    check_schema("run", doc)
    assert keys_without_unit(doc) == []
    # integers stay integers (JSON Schema's "integer" also admits 6.0)
    assert all(isinstance(r["steps"], int) for r in doc["validation"]["runs"])
    assert all(isinstance(c["steps"], int) for c in doc["validation"]["by_controller"].values())


def test_schema_catches_a_unitless_or_mistyped_key(golden_run):
    doc, _ = golden_run
    bad = json.loads(json.dumps(doc))
    side = bad["flowfit"]["supply"]
    side["C"] = side.pop("C_mm3_s_deg2_sqrtMPa")
    with pytest.raises(jsonschema.ValidationError):
        check_schema("run", bad)
    assert "/flowfit/supply/C" in keys_without_unit(bad)
    bad = json.loads(json.dumps(doc))
    bad["validation"]["runs"][0]["steps"] = "6"
    with pytest.raises(jsonschema.ValidationError):
        check_schema("run", bad)
