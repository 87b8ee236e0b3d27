"""The diagnosis's budget and ``--kinds``: every simulation is counted, a budget that cannot
cover the minimum is refused before any simulation, an unknown kind is refused with a
suggestion; the flow honours ``workers``, ``kinds`` and the task runner it is given.

These tests use the linear stand-in simulator of test_diagnosis.py; `hmflow diagnose
--from-campaign` with a budget as the user types it (refused under the minimum, a budget that
covers it kept, real OPM and Prefect) is in
test_cli_run.test_diagnose_from_a_campaign_goes_into_its_report_and_the_campaign_still_resumes."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from test_diagnosis import _linear_case


# ============================================================================ --kinds
def test_kinds_are_parsed_in_the_library_order_and_unknown_ones_get_a_suggestion():
    from hmcore.diagnosis import KINDS, DiagnosisSettings, parse_kinds

    assert parse_kinds("aquifer_strength, well_skin") == ("well_skin", "aquifer_strength")
    assert parse_kinds(["layer_permeability", "layer_permeability"]) == ("layer_permeability",)
    assert parse_kinds(" ".join(KINDS)) == KINDS
    with pytest.raises(ValueError) as err:
        parse_kinds("well_skn,faults,aquifer_strength")
    text = str(err.value)
    assert "--kinds: unknown kind of extension 'well_skn'" in text
    assert "did you mean 'well_skin'?" in text
    assert "unknown kind of extension 'faults'" in text and "'aquifer_strength'" not in text
    with pytest.raises(ValueError, match="names no family of extensions"):
        parse_kinds(" , ")
    with pytest.raises(ValueError, match="kinds: unknown kind of extension 'skin'"):
        DiagnosisSettings(kinds=("skin",))
    assert DiagnosisSettings(kinds=["well_skin"]).kinds == ("well_skin",)


def test_the_cli_refuses_unknown_kinds_before_anything_starts(tmp_path):
    from typer.testing import CliRunner

    from hmflow.cli import app

    out = CliRunner().invoke(app, ["diagnose", "--kinds", "well_skin,layer_perm",
                                   "--storage", str(tmp_path)], env={"COLUMNS": "200"})
    text = " ".join(out.output.split())
    assert out.exit_code == 2, out.output
    assert "unknown kind of extension 'layer_perm'" in text
    assert "did you mean 'layer_permeability'?" in text and "Traceback" not in out.output
    assert list(tmp_path.iterdir()) == []  # nothing written, nothing started


def test_kinds_limit_the_candidates_searched(tmp_path):
    from hmcore.diagnosis import DiagnosisSettings, diagnose

    case, sim, _ = _linear_case(tmp_path)
    doc = diagnose(case, sim.evaluate_batch,
                   settings=DiagnosisSettings(kinds=("well_skin",), plots=False))
    kinds = {c["kind"] for c in doc["ranking"]["candidates"]}
    assert kinds == {"well_skin"} and len(doc["ranking"]["candidates"]) == 4
    assert list(doc["settings"]["kinds"]) == ["well_skin"]


# ============================================================================ budget
def test_a_budget_under_the_minimum_is_refused_before_any_simulation(tmp_path):
    from hmcore.diagnosis import DiagnosisSettings, budget_problem, diagnose, minimum_runs

    case, sim, truth = _linear_case(tmp_path)
    # 32 candidates and 5 globals: 6 runs to calibrate (the deck's values and a Jacobian)
    # or 1 of a given vector, then 32 probes, up to 2 dated ones and 5 finite differences
    assert minimum_runs(case, DiagnosisSettings(), given=False) == 45
    assert minimum_runs(case, DiagnosisSettings(), given=True) == 40
    assert minimum_runs(case, DiagnosisSettings(kinds=("well_skin",)), given=True) == 10
    assert minimum_runs(case, DiagnosisSettings(kinds=("productivity_change",)), given=True) \
        == 12  # the well-skin probes its date scan reads, and 2 dated ones
    for budget, given in ((8, True), (39, True), (44, False)):
        settings = DiagnosisSettings(budget=budget, plots=False)
        problem = budget_problem(case, settings, given)
        assert problem is not None and problem.where == "--budget"
        assert f"cannot cover the minimum of {40 if given else 45}" in problem.what
        assert "2 for dated candidates" in problem.what
        assert "--kinds" in problem.fix and "\n" not in str(problem)
        with pytest.raises(ValueError, match="cannot cover the minimum"):
            diagnose(case, sim.evaluate_batch, settings=settings,
                     calibrated=truth if given else None)
        assert sim.calls == 0
    assert budget_problem(case, DiagnosisSettings(budget=40), True) is None
    assert budget_problem(case, DiagnosisSettings(), False) is None  # no budget


@pytest.mark.parametrize("budget", [45, 48, 54, 61, 70, 84])
def test_the_budget_counts_every_simulation_from_the_deck_values(tmp_path, budget):
    """Every call of the evaluator counts, whatever step makes it; the calibration's
    Levenberg-Marquardt never overshoots (it used to ask for a batch of trial steps past its
    cap), and the ranking's calls are set aside first, so a budget at the minimum runs."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose

    case, sim, _ = _linear_case(tmp_path)
    doc = diagnose(case, sim.evaluate_batch,
                   settings=DiagnosisSettings(budget=budget, plots=False))
    assert doc["cost"]["simulations"] == sim.calls <= budget
    assert doc["ranking"]["runs"] >= 32 and len(doc["ranking"]["candidates"]) == 32


@pytest.mark.parametrize("budget", [40, 44, 51, 64, 94])
def test_the_budget_counts_every_simulation_from_a_given_vector(tmp_path, budget):
    """`--from-campaign X --budget 8` used to run 10 simulations (the given run and a polish
    that asked for trial steps past its cap) and then fail in the ranking. A given vector with
    a hidden skin to find: never more calls than the budget."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.model.parameters import Parameter

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    case, sim, truth = _linear_case(tmp_path, hidden, 12.0)
    start = {**truth, "permx_mult": 1.2}
    doc = diagnose(case, sim.evaluate_batch, calibrated=start,
                   settings=DiagnosisSettings(budget=budget, plots=False))
    assert doc["cost"]["simulations"] == sim.calls <= budget
    if budget >= 90:
        assert doc["selected"] and doc["selected"]["id"] == "well_skin:PROD3"


def test_lockstep_never_evaluates_more_than_its_limit():
    from hmcore.diagnosis.recalibrate import LevenbergMarquardt, LMSettings, run_lockstep

    target = np.array([0.3, -0.2, 0.5])

    def evaluate(batch):
        return [(np.r_[np.sin(u - target), 0.1 * (u - target) ** 2], None) for _, u in batch]

    for limit in range(0, 30):
        lms = [LevenbergMarquardt(np.zeros(3), LMSettings(max_evaluations=12, trials=2))
               for _ in range(2)]
        calls = []

        def counted(batch):
            calls.append(len(batch))
            return evaluate(batch)

        spent = run_lockstep(lms, counted, workers=3, limit=limit)
        assert spent == sum(calls) <= limit
        if limit < 4:  # not even one start point and its Jacobian
            assert all(m.best is None and m.reason == "simulation budget spent" for m in lms)
    # no limit: as before, every minimiser runs to its own cap (+ one round of trials)
    lms = [LevenbergMarquardt(np.zeros(3), LMSettings(max_evaluations=12, trials=2))]
    assert run_lockstep(lms, evaluate) == lms[0].n_evaluations


# ============================================================================ the flow
class _Stop(Exception):
    pass


def test_the_flow_honours_workers_kinds_and_the_task_runner(tmp_path, monkeypatch):
    """`flows.diagnose` passes ``workers`` to the diagnosis (the recalibration batches) and to
    the campaign's task-runner factory with the runner and Dask address given, and the kinds
    to search; a budget under the minimum ends the run before the diagnosis exists."""
    import flows.diagnose as fd

    (tmp_path / "c").mkdir()
    case, _, _ = _linear_case(tmp_path / "c")
    seen: dict = {}

    class Runner:
        def __init__(self, kind, workers, address, cluster=None):  # issue 43: the case's [cluster]
            seen["runner"] = (kind, workers, address)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    class Stub:
        def __init__(self, loaded, evaluate_batch, settings, log=None):
            seen["settings"] = settings

        def calibrate(self, *a):
            raise _Stop()

    class Version:
        def ref(self):
            return {"step": "case"}

    monkeypatch.setattr(fd, "get_run_logger", lambda: logging.getLogger("test"))
    monkeypatch.setattr(fd, "prepare_deck", lambda *a: Version())
    monkeypatch.setattr(fd, "make_runner", Runner)
    monkeypatch.setattr("hmcore.diagnosis.rounds.Diagnosis", Stub)
    monkeypatch.setattr("flows.refuse.get_run_logger", lambda: logging.getLogger("test"))
    with pytest.raises(_Stop):
        fd.diagnose_flow.fn(case=str(case.source), storage=str(tmp_path / "s"), workers=3,
                            task_runner="dask", dask_address="tcp://head:8786",
                            kinds=["aquifer_strength", "well_skin"], budget=200)
    assert seen["runner"] == ("dask", 3, "tcp://head:8786")
    assert seen["settings"].workers == 3 and seen["settings"].budget == 200
    assert seen["settings"].kinds == ("well_skin", "aquifer_strength")
    seen.clear()
    state = fd.diagnose_flow.fn(case=str(case.source), storage=str(tmp_path / "s"), budget=8,
                                calibrated={"skin": 1.0})
    assert state.is_failed() and "cannot cover the minimum of 40" in state.message
    state = fd.diagnose_flow.fn(case=str(case.source), storage=str(tmp_path / "s"),
                                kinds=["well_skn"])
    assert state.is_failed() and "did you mean 'well_skin'?" in state.message
    state = fd.diagnose_flow.fn(case=str(case.source), storage=str(tmp_path / "s"),
                                settings={"chi2": 3.0})
    assert state.is_failed() and "unknown field(s) ['chi2']" in state.message
    assert seen == {}  # no diagnosis, no runner

