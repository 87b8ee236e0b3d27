"""What would separate two explanations, on real OPM Flow runs of the small synthetic case
(conftest.small_case): two models that explain one well's pressure differently - a skin on
the well and a low-permeability box around it (the pair `hmflow diagnose --kinds
well_skin,regional_permeability` weighs) - given as an ambiguous answer (equal fits), get the
well, response and day where their predictions differ most in noise sigmas, from their runs.

Two simulations; the diagnosis's own weighing is tested without a simulator
(tests/test_diagnosis_evidence.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hmcore.diagnosis.answer import section
from hmcore.diagnosis.evidence import Fit
from hmcore.diagnosis.candidate import extended_space
from hmcore.diagnosis.extensions import build_candidates
from hmcore.diagnosis.runs import Simulations, local_evaluator
from hmcore.diagnosis.separation import LINE, MEASURED
from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH
from hmcore.scoring.observations import ObservationSet


def test_an_ambiguous_pair_gets_the_measurement_that_separates_it(small_case, tmp_path):
    from hmcore.cases import load_case

    case = load_case(small_case)
    values = {n: SYNTHETIC_TRUTH[n] for n in case.space.names}
    cands = build_candidates(case.info, case.space, values,
                             ("well_skin", "regional_permeability"))
    well = next(c.wells[0] for c in cands if c.kind == "regional_permeability")
    skin = next(c for c in cands if c.kind == "well_skin" and c.wells[0] == well)
    box = next(c for c in cands if c.kind == "regional_permeability" and c.wells[0] == well)
    union = case.with_space(extended_space(case.space, [skin, box]))
    obs = ObservationSet.from_case(case)
    sims = Simulations(local_evaluator(tmp_path / "runs", workers=2), None, lambda m: None)
    neutral = {skin.name: skin.neutral, box.name: box.neutral}
    runs = sims.run(union, [{**values, **neutral, skin.name: skin.parameter.high * 0.6},
                            {**values, **neutral, box.name: box.parameter.low * 2.0}],
                    "separation", obs)
    assert all(r.ok for r in runs), [getattr(r.result, "reason", "") for r in runs]
    eig = np.full(len(case.space.parameters) + 1, 100.0)
    fits = [Fit(skin.id, skin.kind, 500.0, 100.0, eig), Fit(box.id, box.kind, 500.0, 100.0, eig)]
    answer = section(fits, 400, {skin.id: runs[0], box.id: runs[1]}, obs)
    assert answer["kind"] == "set" and set(answer["members"]) == {skin.id, box.id}
    (sep,) = answer["separations"]
    assert sep["quantity"] in MEASURED and sep["z"] >= LINE and sep["from_day"] is not None
    assert sep["from_day"] <= sep["day"]
    # the sentence names the measurement, and it is what the runs say
    assert f"measurement at {sep['well']}" in sep["sentence"] and sep["sentence"] in answer["text"]
    frames = [r.responses for r in runs]
    values_at = [f[(f.well == sep["well"]) & (f.quantity == sep["quantity"])
                   & (f.days == sep["day"])]["value"].iloc[0] for f in frames]
    sigma = obs.rows[(obs.rows.well == sep["well"]) & (obs.rows.quantity == sep["quantity"])
                     ]["sigma"].median()
    assert abs(values_at[0] - values_at[1]) / sigma == pytest.approx(sep["z"], rel=1e-6)
