"""One round of the diagnosis of a calibrated case: what does the model get wrong, and which
extension fixes it?

The steps, each a function of the earlier steps' frozen results (:mod:`hmcore.diagnosis.state`)
that returns its own:

1. calibrate   - the case's own (global) parameters and the noise model of their residuals
   (:mod:`hmcore.diagnosis.calibration`);
2. analyse     - residual statistics per well, response and period against the noise level
   (:func:`hmcore.diagnosis.residuals.analyse_residuals`);
3. rank        - every candidate extension's score test, with probes of dated productivity
   changes and moved regional boxes (:mod:`hmcore.diagnosis.ranking`);
4. extend      - the extended models of the leading candidates
   (:func:`hmcore.diagnosis.recalibration.extend`);
5. recalibrate - those models recalibrated together, some restarted from the deck's values,
   each judged by the fit line and the held-back rule (:mod:`hmcore.diagnosis.recalibration`,
   :mod:`hmcore.diagnosis.restart`, :mod:`hmcore.diagnosis.confirmation`);
6. decide      - the ranked causes, the selected extension, the verdict: the round's document
   (:mod:`hmcore.diagnosis.decision`, :func:`document`), and the answer: every explanation
   weighed by its evidence, one cause or the set the data cannot separate with what would
   separate it (:mod:`hmcore.diagnosis.answer`);
7. report      - ``diagnosis.json``, ``report.md`` and residual plots
   (:mod:`hmcore.diagnosis.report`).

:class:`Diagnosis` runs them one at a time, so that the Prefect flow can store each step's
artifacts; :mod:`hmcore.diagnosis.rounds` runs the rounds and windows
(:func:`hmcore.diagnosis.rounds.diagnose`).

The simulator is never run here: ``evaluate_batch(case, values_list, step) -> results`` is
injected (:mod:`hmcore.diagnosis.runs`). Every call counts against
``DiagnosisSettings.budget``; a budget below :func:`minimum_runs` is refused before the first
(:func:`budget_problem`).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Callable

from hmcore.diagnosis import answer, calibration, decision, ranking, recalibration
from hmcore.diagnosis.budget import budget_problem, count_tests, minimum_runs
from hmcore.diagnosis.candidate import Candidate
from hmcore.diagnosis.recalibrate import Coordinates
from hmcore.diagnosis.report import write_report
from hmcore.diagnosis.residuals import analyse_residuals
from hmcore.diagnosis.runs import (EvaluateBatch, Run, Simulations, heldout_per_well,
                                   local_evaluator, rescore, run_scores)
from hmcore.diagnosis.settings import DiagnosisSettings, with_lines
from hmcore.diagnosis.state import Context, Round
from hmcore.model.case import Case
from hmcore.scoring.observations import ObservationSet

__all__ = ["Diagnosis", "EvaluateBatch", "Run", "budget_problem", "document",
           "local_evaluator", "minimum_runs"]
"""Besides this module's own: the names callers import from here (``hmflow``'s budget check,
:mod:`hmcore.diagnosis.rounds`), whose homes are :mod:`~hmcore.diagnosis.budget` and
:mod:`~hmcore.diagnosis.runs`."""


class Diagnosis:
    """One round of a diagnosis, step by step (see the module docstring).

    Holds the round's :class:`hmcore.diagnosis.state.Context` (fixed) and its ``state``, the
    frozen results of the steps run so far (a :class:`hmcore.diagnosis.state.Round`, replaced
    by each step as it ends). The properties read the stored steps' documents and the runs the flow and the
    later rounds need."""

    def __init__(self, case: Case, evaluate_batch: EvaluateBatch,
                 settings: DiagnosisSettings | None = None,
                 log: Callable[[str], None] | None = None):
        settings = settings or DiagnosisSettings()
        n_tests = count_tests(case, settings)
        settings = with_lines(settings, n_tests)
        obs = ObservationSet.from_case(case, settings.heldout_fraction)
        if case.history_end_days is None:  # score E on the same split as the residuals
            case = dataclasses.replace(case, history_end_days=obs.history_end_days)
        log = log or (lambda msg: None)
        self._context = Context(case, settings, obs, Coordinates(case.space.parameters),
                               Simulations(evaluate_batch, settings.budget, log), n_tests,
                               log, time.perf_counter())
        self._state = Round()

    # ------------------------------------------------------------------ the steps
    def calibrate(self, calibrated: dict[str, float] | None = None,
                  initial: dict[str, float] | None = None, result: Any = None) -> dict:
        """Step 1 (:func:`hmcore.diagnosis.calibration.calibrate`); ``calibration.json``."""
        t0 = time.perf_counter()
        cal = calibration.calibrate(self._context, calibrated, initial, result)
        self._done("calibrate", t0, calibrated=cal)
        return cal.document

    def analyse(self) -> dict:
        """Step 2: the residual analysis of the calibrated model; ``residuals.json``."""
        t0 = time.perf_counter()
        residuals = analyse_residuals(self.obs, self.base.responses)
        self._done("analyse", t0, residuals=residuals)
        self.log(f"residuals: {len(residuals['flags'])} findings beyond noise")
        return residuals

    def rank(self) -> dict:
        """Step 3 (:func:`hmcore.diagnosis.ranking.rank`); ``ranking.json``."""
        t0 = time.perf_counter()
        result = ranking.rank(self._context, self._state.calibrated)
        self._done("rank", t0, ranking=result)
        return result.document

    def extend(self) -> dict:
        """Step 4 (:func:`hmcore.diagnosis.recalibration.extend`); ``extension.json``."""
        st = self._state
        result = recalibration.extend(self._context, st.calibrated, st.ranking)
        self._state = dataclasses.replace(st, extension=result)
        return result.document

    def recalibrate(self) -> dict:
        """Step 5 (:func:`hmcore.diagnosis.recalibration.recalibrate`);
        ``recalibration.json``."""
        t0 = time.perf_counter()
        st = self._state
        result = recalibration.recalibrate(self._context, st.calibrated, st.ranking,
                                           st.extension)
        self._done("recalibrate", t0, recalibration=result)
        return result.document

    def decide(self) -> dict:
        """Step 6: the round's document (:func:`document`)."""
        doc = document(self._context, self._state)
        self._state = dataclasses.replace(self._state, document=doc)
        return doc

    def report(self, out_dir: Path | None = None, doc: dict | None = None,
               extended: Run | None = None) -> dict:
        """Step 7: write diagnosis.json, report.md and the residual plots into ``out_dir``:
        this round's document, or ``doc`` (rounds combined) with ``extended`` the run plotted
        against the calibrated model (default: the shown candidate's)."""
        doc = doc or self._state.document or self.decide()
        if out_dir is None:
            return {}
        shown = doc["per_well_response"]["extension"]
        ext = extended if extended is not None else \
            (self.confirmed_runs.get(shown) if shown else None)
        return write_report(out_dir, doc, self.case, self.obs, self.base.responses,
                            ext.responses if ext is not None else None, self.settings.plots)

    def _done(self, step: str, t0: float, **results: Any) -> None:
        self._state = dataclasses.replace(
            self._state, timings={**self._state.timings, step: time.perf_counter() - t0},
            **results)

    # ------------------------------------------------------------------ what it holds
    @property
    def context(self) -> Context:
        """What every step works with (the case, the settings, the simulations)."""
        return self._context

    @property
    def state(self) -> Round:
        """The frozen results of the steps run so far."""
        return self._state

    @property
    def case(self) -> Case:
        return self._context.case

    @property
    def settings(self) -> DiagnosisSettings:
        return self._context.settings

    @property
    def log(self) -> Callable[[str], None]:
        return self._context.log

    @property
    def evaluate_batch(self) -> EvaluateBatch:
        return self._context.sims.evaluate_batch

    @property
    def n_runs(self) -> int:
        """Simulator calls made so far."""
        return self._context.sims.n_runs

    @property
    def sim_time_s(self) -> float:
        return self._context.sims.sim_time_s

    def left(self, reserve: int = 0) -> int | None:
        """Simulator calls left of the budget after ``reserve`` more (None: no budget)."""
        return self._context.sims.left(reserve)

    @property
    def obs(self) -> ObservationSet:
        """The noise model: refined from the calibrated model's residuals once calibrated."""
        cal = self._state.calibrated
        return cal.obs if cal is not None else self._context.obs

    @property
    def base(self) -> Run | None:
        """The calibrated model's run."""
        cal = self._state.calibrated
        return cal.run if cal is not None else None

    @property
    def calibration(self) -> dict:
        cal = self._state.calibrated
        return cal.document if cal is not None else {}

    @property
    def residuals(self) -> dict:
        return self._state.residuals or {}

    @property
    def candidates(self) -> tuple[Candidate, ...]:
        r = self._state.ranking
        return r.candidates if r is not None else ()

    @property
    def ranking(self) -> dict:
        r = self._state.ranking
        return r.document if r is not None else {}

    @property
    def sensitivity(self) -> dict:
        r = self._state.ranking
        return r.sensitivity if r is not None else {}

    @property
    def extension(self) -> dict:
        e = self._state.extension
        return e.document if e is not None else {}

    @property
    def recalibration(self) -> dict:
        r = self._state.recalibration
        return r.document if r is not None else {}

    @property
    def confirmed(self) -> dict[str, dict]:
        """Per recalibrated candidate id, its record."""
        r = self._state.recalibration
        return r.confirmed if r is not None else {}

    @property
    def confirmed_runs(self) -> dict[str, Run]:
        """Per recalibrated candidate id, the run of its recalibrated model."""
        r = self._state.recalibration
        return r.runs if r is not None else {}

    def rescore(self, run: Run) -> Run:
        """``run`` with its residuals whitened under this round's noise model."""
        return rescore(run, self.obs)

    def run_scores(self, run: Run) -> dict:
        """E, per-response and per-well-response misfits, SSRs of ``run`` on this case."""
        return run_scores(self.case, run)


def document(ctx: Context, state: Round) -> dict:
    """The round's document (``diagnosis.json`` of one round): the ranked causes, the selected
    extension (or null), the verdict, the gain, the statistic and every step's document."""
    s, case = ctx.settings, ctx.case
    cal, rank, recal = state.calibrated, state.ranking, state.recalibration
    base, obs = cal.run, cal.obs
    candidates = list(rank.candidates)
    confirmed = recal.confirmed
    residuals = state.residuals or {}
    base_sc = run_scores(case, base)
    base_ho = heldout_per_well(case, base.responses)
    d = decision.decide(
        candidates, rank.scores, confirmed, rank.document, base_sc, base_ho,
        obs.n_noise("heldout"),
        {"n_fit": obs.n_fit, "n_heldout": obs.n_heldout,
         "n_fit_measured": obs.n_noise("fit"),
         "n_heldout_measured": obs.n_noise("heldout")},
        obs.history_end_days, s, residuals)
    shown = d.shown
    per_well = decision.per_well_table(
        base_sc["per_well_response"], base_ho,
        confirmed[shown]["per_well_response_after"] if shown else None,
        confirmed[shown]["per_well_response_heldout_after"] if shown else None)
    by_id = {c.id: c for c in candidates}
    selected = None
    if d.selected is not None:
        sel = d.selected
        selected = {**decision.cause(by_id[sel], rank.scores.get(sel), confirmed.get(sel),
                                     "selected"),
                    "values": confirmed[sel]["values"]}
    doc = {
        "case": case.name, "source": str(case.source),
        "history_end_days": obs.history_end_days,
        "parameters": case.space.names,
        "calibrated": base.values,
        "causes": d.causes,
        "selected": selected,
        "accepted": ([decision.accepted_cause(selected, confirmed[d.selected], 1)]
                     if selected else []),
        "fits_beyond_noise": list(d.fits),
        "statistic": decision.statistic(
            confirmed, d.fits, base.ssr_fit, ctx.n_tests, s,
            {c.id for c in candidates if c.details.get("start_day") is not None},
            obs.n_noise("fit")),
        "verdict": d.verdict,
        "heldout_within_noise": d.heldout_quiet,
        "gain": d.gain,
        "per_well_response": {"extension": shown, "rows": per_well},
        "candidates_recalibrated": confirmed,
        "residuals": residuals,
        "ranking": rank.document,
        "calibration": cal.document,
        "settings": s.to_dict(),
        "cost": {"simulations": ctx.sims.n_runs, "sim_time_s": ctx.sims.sim_time_s,
                 "wall_time_s": time.perf_counter() - ctx.started,
                 "steps_s": dict(state.timings)},
    }
    st = doc["statistic"]
    share = st and st["vs_none"]["share"]
    if selected and st["cause"] == d.selected and share is not None and \
            share < s.partial_share:
        doc["verdict"] += (
            f" ({d.selected} removes only {100 * share:.0f} % of the fitted misfit beyond "
            "noise: something else acts too)")
    return answer.attach(doc, ctx, state)
