"""Dynamic effects found in position-control data on the identified twin
(the ``identify`` stage ran before ``discover``).

An extra transport delay between the servo and the needle does not show in
the servo's feedback: identify's line (bulk modulus) takes part of it, and
discover must still name it, refitting the line with the candidate, and
cut the held-out flow error of the runs re-run in closed loop on the twin,
segment by segment from the logged state.
"""
from __future__ import annotations

import pytest

from seanv_analysis.sim import simulate_scenario
from seanv_analysis.stages import run_stages


@pytest.fixture(scope="module")
def delayed_position(tmp_path_factory):
    root = tmp_path_factory.mktemp("twin") / "position"
    simulate_scenario("paper-position", root, seed=3, effects=["delay:delay_s=0.1"])
    return root


def test_extra_delay_named_on_the_identified_twin(delayed_position):
    ctx = run_stages(delayed_position, ["ingest", "identify", "discover"],
                     options={"identify": {"parts": ["servo", "flow_path"]}})
    d = ctx.result("discover").discovery
    assert d.verdict == "effect_found"
    assert [(e.name, e.side) for e in d.effects] == [("delay", "both")]
    found = d.effects[0].params["delay_s"]
    lo, hi = d.effects[0].params_ci95["delay_s"]
    assert found == pytest.approx(0.1, abs=0.02) and lo <= 0.1 <= hi, (found, lo, hi)
    assert d.heldout_source == "closed_loop_heldout"     # each segment re-run
    assert d.rmse_after_mm3_s <= 0.7 * d.rmse_before_mm3_s
    pc = d.position_control
    assert pc["found"] and pc["n_heldout_runs"] == 1
    kept = next(c for c in pc["candidates"] if c["named"])
    # the closed-loop numbers are there beside the headline
    assert kept["heldout_before"]["fit_position_pct"] > 0 and kept["heldout_after"]
    # the closed-loop check runs the twin with the line refitted with the effect
    assert d.twin_overrides["tube"]["effective_bulk_modulus_mpa"] > 0


def test_closed_loop_check_survives_effects_that_cannot_be_simulated(monkeypatch):
    """An effect the simulator refuses (field data: discover picked a negative
    delay, the effect's own range check refused it) leaves the closed-loop
    check with the base model and a note, not an UnboundLocalError."""
    from types import SimpleNamespace

    from seanv_analysis.errors import ConfigError
    from seanv_analysis.stages import discover as stage

    seen = {}

    class Disc:
        effects = [SimpleNamespace(name="delay")]
        proposed_term = None
        model = "base model"
        base_model = "start model"
        twin_overrides = {"tube": {"effective_bulk_modulus_mpa": 120.0}}

        def augmented_model_and_effects(self, rig):
            raise ConfigError("effect 'delay': delay_s = -0.038 s; expected >= 0")

        def with_closed_loop(self, before, after):
            seen["checked"] = (before, after)
            return self

    def fake_validate(ctx, model, specs=(), *, stage="validate", plant_overrides=None):
        seen[stage] = (model, list(specs), plant_overrides)
        return SimpleNamespace(validation=stage, failed=())

    monkeypatch.setattr(stage, "position_paths", lambda ctx: ["run"])
    monkeypatch.setattr(stage, "validate_model", fake_validate)
    monkeypatch.setattr(stage, "controller_numbers", lambda v: v)
    ctx = SimpleNamespace(plant_rig=None, valve="valve", result=lambda name: None)
    res = stage.closed_loop(ctx, Disc())
    assert "effects not simulated in the closed-loop check" in res.note
    assert "-0.038" in res.note
    assert seen["validate"][0] == "start model"
    assert seen["validate_augmented"] == ("base model", [], Disc.twin_overrides)
    assert seen["checked"] == ("validate", "validate_augmented")
