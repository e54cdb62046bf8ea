"""The JSON outputs follow their schemas (data_schema/json/) and name the
unit of every number in its key. Each command's ``--json`` is checked in its
own CLI test (tests/test_cli_*.py); the whole pipeline's result.json, which
holds every stage's contract, in tests/test_golden.py (it shares the golden
pipeline run)."""
from __future__ import annotations

import json

import pytest
from json_schemas import SCHEMAS

jsonschema = pytest.importorskip("jsonschema")


def test_schema_files_are_valid_draft_2020_12():
    names = sorted(p.name.split(".")[0] for p in SCHEMAS.glob("*.schema.json"))
    assert names == ["common", "discover", "flowfit", "identify", "ingest", "run", "tracking",
                     "validate"]
    for path in SCHEMAS.glob("*.schema.json"):
        jsonschema.Draft202012Validator.check_schema(json.loads(path.read_text()))
