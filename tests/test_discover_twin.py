"""The closed-loop check of discover's stage. An extra delay named on a twin
(identified by the identify stage or by discover itself) is checked end to
end by tests/test_discover_sim.py (discover alone, our simulator) and
tests/test_identify.py (identify + discover, the foreign rig)."""
from __future__ import annotations


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

        def position_run_model_and_effects(self, rig):
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
