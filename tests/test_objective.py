"""One objective (issue 47): the case file says what a campaign minimises and selects by, the
best call is the minimum of that objective under the noise the campaign ended with, the noise
is refined from the best call so far and a resumed campaign refines it identically (fake
simulator: records carry the simulated value of every observed row, as a campaign's do)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from hmcore.calibration.calls import MAX_REFINEMENTS, BudgetedCalls
from hmcore.calibration.loop import best_record, calibrate
from hmcore.calibration.methods import make_proposer
from hmcore.calibration.objective import Objective
from hmcore.errors import CaseError
from hmcore.model.case import load_case_file
from hmcore.model.parameters import Parameter, ParameterSpace
from hmcore.scoring.misfit import category_ranges
from hmcore.scoring.observations import ObservationSet
from storage import ArtifactStore, EvaluationJournal
from tasks.results import archive_best, consolidate

SPACE = ParameterSpace(parameters=(
    Parameter(name="a", kind="multiply", keywords=("PORO",), low=0.5, high=2.0),
    Parameter(name="b", kind="skin", low=-5.0, high=15.0)))
DAYS = np.arange(30.0, 30.0 * 41, 30.0)
TRUE = (0.3, -0.2)


def curves(u) -> dict[str, np.ndarray]:
    """The fake simulator's responses at action ``u``: BHP and oil rate of one well."""
    a, b = u
    t = DAYS / DAYS[-1]
    return {"WBHP": 200.0 - 40.0 * t + 25.0 * a * t + 10.0 * b * t * t,
            "WOPR": 100.0 * (1.0 - 0.3 * t) * (1.0 + 0.2 * b)}


def observed_frame() -> pd.DataFrame:
    """The history of the truth with noise of 2 bar (BHP) and 1 % (oil), no sigma column."""
    rng = np.random.default_rng(5)
    c = curves(TRUE)
    rows = []
    for q, sd in (("WBHP", 2.0), ("WOPR", 0.01)):
        noise = rng.standard_normal(DAYS.size) * (sd if q == "WBHP" else sd * c[q])
        rows.append(pd.DataFrame({"well": "P1", "quantity": q, "days": DAYS,
                                  "value": c[q] + noise, "flowing": True, "derived": False}))
    return pd.concat(rows, ignore_index=True)


def objective_of(name: str) -> Objective:
    obs_frame = observed_frame()
    obs = ObservationSet.from_observed(obs_frame, float(DAYS[-10]), 15.0)
    return Objective(name, obs, obs_frame, obs_frame, category_ranges(obs_frame))


def evaluator(objective: Objective, journal: EvaluationJournal | None = None,
              other_E: bool = False):
    """Records as a campaign writes them: E (the paper's, of BHP and oil; ``other_E``: a
    misfit whose minimum lies elsewhere, so that the two objectives choose different calls),
    ``simulated``."""
    obs = objective.observations

    def batch(jobs):
        out = []
        for j in jobs:
            c = curves(np.clip(np.asarray(j.action, float), -1, 1))
            sim = np.array([c[q][np.argmin(np.abs(DAYS - d))] for q, d in
                            zip(obs.rows.quantity, obs.rows.days)])
            fit = obs.rows.period.to_numpy() == "fit"
            E = float(np.mean([np.mean(((sim - obs.rows.observed.to_numpy())[
                fit & (obs.rows.quantity.to_numpy() == q)] / objective.ranges[cat]) ** 2)
                for q, cat in (("WBHP", "bhp"), ("WOPR", "oil"))]))
            if other_E:
                E = 0.01 * float(np.sum((np.asarray(j.action) - [-0.8, 0.9]) ** 2))
            rec = {"index": j.index, "action": list(j.action), "params": j.values,
                   "phase": j.phase, "status": "COMPLETE", "E": E, "penalty": 0.0,
                   "reward": -E, "simulated": sim.tolist(), "run_dir": ""}
            if journal is not None:
                journal.record(j.index, rec)
            out.append(rec)
        return out
    return batch


def campaign(name: str, method: str = "lm", budget: int = 24, done=None, journal=None):
    objective = objective_of(name)
    heard: list[Objective] = []
    proposer = make_proposer(method, SPACE.dim, 3, 2, budget)
    records = calibrate(proposer, SPACE, evaluator(objective, journal), budget, 2, done,
                        objective=objective, on_refine=heard.append)
    return records, heard


# ----------------------------------------------------------------------------- the case file
def test_an_unknown_objective_is_refused_with_the_file_and_the_key(tmp_path: Path):
    case = tmp_path / "case.toml"
    case.write_text('[case]\nname = "x"\ndeck = "missing.DATA"\nobserved = "o.csv"\n'
                    '[misfit]\nobjective = "chi2"\n')
    with pytest.raises(CaseError) as err:
        load_case_file(case)
    hits = [p for p in err.value.problems if "misfit.objective" in p.where]
    assert hits and str(case) in hits[0].where and "'likelihood'" in hits[0].what \
        and "'E'" in hits[0].what, err.value.problems


def test_the_default_objective_is_the_likelihood():
    from hmcore.model.case import MisfitSettings

    assert MisfitSettings().objective == "likelihood"
    assert MisfitSettings(objective="E").objective == "E"


# ----------------------------------------------------------------------------- values
def test_E_residuals_square_to_E_and_likelihood_residuals_to_n_times_the_likelihood():
    for name in ("E", "likelihood"):
        objective = objective_of(name)
        (rec,) = evaluator(objective)([_job(np.array([0.1, 0.4]))])
        r = objective.residuals(rec)
        n = objective.observations.n_noise("fit") if name == "likelihood" else 1
        assert float(r @ r) / n == pytest.approx(objective.value(rec), rel=1e-9)
    assert objective.value(rec) != pytest.approx(rec["E"])


def _job(u):
    from hmcore.calibration.calls import Job

    return Job(0, SPACE.to_values(u), tuple(u), 0, "explore")


# ----------------------------------------------------------------------------- the best call
@pytest.mark.parametrize("name", ["likelihood", "E"])
def test_the_best_call_of_a_campaign_is_the_minimum_of_its_stated_objective(tmp_path, name):
    """Through the campaign's own consolidation and archive: the best call is the COMPLETE
    call of the lowest value of the case's objective under the noise the campaign ended with
    (for the likelihood not the call of the lowest E)."""
    store = ArtifactStore(tmp_path)
    journal = EvaluationJournal(store, "c")
    objective = objective_of(name)
    calls = BudgetedCalls(SPACE, evaluator(objective, journal, other_E=True), 30,
                          objective=objective)
    rng = np.random.default_rng(0)
    records = calls.run(rng.uniform(-1, 1, (30, 2)))
    calls.refine_noise()
    final = calls.objective
    results = consolidate.fn(str(tmp_path), "c", SPACE.names, final)
    best = archive_best.fn(str(tmp_path), "c", results).read_json("metrics.json")
    values = [final.value(r) for r in records]
    assert best["index"] == records[int(np.argmin(values))]["index"]
    assert best["objective"] == name
    if name == "likelihood":
        assert final.refinement == 1  # the estimate was refined from the best call
        assert best["index"] != records[int(np.argmin([r["E"] for r in records]))]["index"]
    doc = results.read_json("records.json")
    assert best_record(doc["records"], name)["index"] == best["index"]


# ----------------------------------------------------------------------------- refinement
def test_lm_refines_the_noise_from_its_best_call_and_a_resumed_campaign_does_the_same():
    records, heard = campaign("likelihood", budget=30)
    assert 1 <= len(heard) <= MAX_REFINEMENTS
    froms = [o.refined_from for o in heard]
    assert len(set(froms)) == len(froms)  # each from another best call
    # the refined BHP noise is near the 2 bar of the data (the estimate from the series
    # alone is what refinement corrects)
    rows = heard[-1].observations.rows
    bhp = rows[(rows.quantity == "WBHP") & (rows.period == "fit")].sigma.median()
    assert 1.2 < bhp < 3.2
    # resumed from the journal of its first 17 calls: the same calls, the same noise
    done = {r["index"]: r for r in records[:17]}
    again, heard_again = campaign("likelihood", budget=30, done=done)
    assert [r["action"] for r in again] == [r["action"] for r in records]
    assert [o.refined_from for o in heard_again] == froms
    np.testing.assert_array_equal(heard_again[-1].observations.rows.sigma, rows.sigma)


def test_the_E_objective_never_refines_and_tells_a_proposer_the_reward():
    records, heard = campaign("E", method="random", budget=12)
    assert heard == [] and len(records) == 12
    objective = objective_of("E")
    f = objective.feedback(records[0])
    assert f.reward == records[0]["reward"] and f.e_obs == records[0]["E"]


def test_a_stated_or_given_noise_is_never_refined():
    obs_frame = observed_frame().assign(sigma=1.0)
    obs = ObservationSet.from_observed(obs_frame, float(DAYS[-10]), 15.0)
    objective = Objective("likelihood", obs, obs_frame, obs_frame, category_ranges(obs_frame))
    assert not objective.refinable
    calls = BudgetedCalls(SPACE, evaluator(objective), 4, objective=objective)
    calls.run(np.zeros((2, 2)) + [[0.0, 0.0], [0.2, 0.1]])
    assert not calls.refine_noise() and calls.objective is objective


# ----------------------------------------------------------------------------- campaign and report
def test_a_campaign_chosen_by_E_before_the_objective_existed_resumes_only_under_E(tmp_path):
    from flows.campaign import check_campaign_settings

    settings = {"agent": "cmaes", "seed": 0, "workers": 2}
    ArtifactStore(tmp_path).bind_settings("old", settings)  # stored without an objective
    check_campaign_settings(str(tmp_path), "old", {**settings, "objective": "E"})
    with pytest.raises(ValueError, match='objective = "E"'):
        check_campaign_settings(str(tmp_path), "old", {**settings, "objective": "likelihood"})


def test_the_report_shows_both_numbers_and_says_which_chose():
    from hmcore.reporting.report import Choice, build_report

    table = pd.DataFrame({"index": [0, 1], "status": ["COMPLETE"] * 2, "E": [0.02, 0.01],
                          "likelihood": [1.5, 2.5], "best_E_so_far": [0.02, 0.01],
                          "best_objective_so_far": [1.5, 1.5], "sim_time_s": [1.0, 1.0],
                          "wall_time_s": [1.0, 1.0], "failure": [None, None]})
    best = {"index": 0, "E": 0.02, "likelihood": 1.5, "params": {"a": 1.0},
            "metrics": {"macro": {"nmse": 0.1, "r2": 0.5, "cmatch": 90.0}, "categories": {},
                        "wells": {}, "excluded": {}}}
    refs = {"floor": {"E": 0.009, "likelihood": 1.1}, "centre": {"E": 0.05, "likelihood": 9.0}}
    text, doc = build_report("c", {"name": "x", "source": "x.toml", "parameters": []}, table,
                             best, None, choice=Choice("likelihood", {"refinement": 2,
                                                                      "refined_from_call": 0},
                                                       refs))
    assert "## Best case: call 1 of 2 (likelihood = 1.500000)" in text
    assert "Chosen by the likelihood" in text
    assert "| best (call 1) | **1.500000** | 0.020000 |" in text
    assert "| truth / deck values | **1.100000** | 0.009000 |" in text
    assert "refined 2 time(s)" in text and "best likelihood so far (chooses)" in text
    assert doc["best"]["chosen_by"] == "likelihood" and doc["objective"] == "likelihood"
