"""The diagnosis of a calibrated case, step by step: what does the model get wrong, and which
extension fixes it?

Steps (each a method of :class:`Diagnosis`, so the Prefect flow can store every step's
artifacts; :func:`diagnose` runs them all):

1. ``calibrate``  - the case's own (global) parameters by bounded Levenberg-Marquardt on the
   whitened residuals of the fitted history, or a given calibrated vector evaluated once;
2. ``analyse``    - residual statistics per well, response and period against the noise level
   (:func:`hmcore.diagnosis.residuals.analyse_residuals`);
3. ``rank``       - one finite-difference run per candidate extension (and per global
   parameter for a fresh Jacobian), all in one parallel batch; score test with the globals
   projected out (:mod:`hmcore.diagnosis.screening`); then probes of what that batch points
   to: dated productivity changes (:mod:`hmcore.diagnosis.dating`) and the boxes of the
   strongest regional candidates moved beside their wells
   (:func:`hmcore.diagnosis.extensions.shifted_regions`), all ranked together;
4. ``extend``     - the extended models of the leading candidates (globals + one new
   parameter each), warm-started at the calibrated point with the linear model's step;
5. ``recalibrate``- the extended models recalibrated together (lockstep LM, Broyden Jacobian
   updates), restarted from the deck's values when the calibration left globals at their
   bounds or the held-back history vetoes the best fits (:mod:`hmcore.diagnosis.refit`);
   the gain on the fitted AND the held-back history;
6. ``decide``     - the ranked causes and the selected extension
   (:mod:`hmcore.diagnosis.decision`);
7. ``report``     - ``diagnosis.json``, ``report.md`` and residual plots.

One round of one fitted window; :mod:`hmcore.diagnosis.rounds` runs the rounds and windows
(:func:`hmcore.diagnosis.rounds.diagnose`).

The simulator is never run here: ``evaluate_batch(case, values_list, step) -> results`` is
injected (results are :class:`hmcore.scoring.evaluation.Evaluation`-like: ``status``, ``E``,
``E_heldout``, ``responses``); :func:`local_evaluator` is a plain thread-pool one. Every call
counts against ``DiagnosisSettings.budget``; a budget below :func:`minimum_runs` is refused
before the first (:func:`budget_problem`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from hmcore.model.case import Case
from hmcore.diagnosis import dating, decision, refit, screening
from hmcore.diagnosis.attribution import Score, projector_basis
from hmcore.diagnosis.extensions import (Candidate, base_values, build_candidates,
                                         SHIFTS, current_skin, dated_productivity,
                                         extended_space, open_end, shifted_regions)
from hmcore.diagnosis.recalibrate import (Coordinates, LevenbergMarquardt, LMSettings, Point,
                                          run_lockstep)
from hmcore.scoring.observations import ObservationSet
from hmcore.diagnosis.residuals import analyse_residuals
from hmcore.diagnosis.settings import DiagnosisSettings, with_lines
from hmcore.errors import Problem
from hmcore.scoring.evaluation import score_responses
from hmcore.ordering import natural_key

EvaluateBatch = Callable[[Case, list[dict[str, float]], str], list[Any]]
REGIONS_PER_WELL = 2
"""Regional boxes of one well (centred or moved) recalibrated at most: the best two by chi2."""


# ============================================================================= budget
def minimum_runs(case: Case, settings: DiagnosisSettings, given: bool) -> int:
    """Simulator calls a diagnosis of ``case`` cannot do without: the calibrated model (one
    run of a ``given`` vector; otherwise the deck's values and their finite differences, one
    run per global parameter), then the ranking (one probe per candidate of
    ``settings.kinds`` and one finite difference per global parameter)."""
    dim = len(case.space.parameters)
    n_candidates = len(build_candidates(case.info, case.space, None, settings.kinds))
    return (1 if given else dim + 1) + n_candidates + _dated_reserve(case, settings) + dim


def _dated_reserve(case: Case, settings: DiagnosisSettings) -> int:
    """Probe runs of the dated candidates the ranking may add (``productivity_change``)."""
    if "productivity_change" not in settings.kinds:
        return 0
    return min(settings.dated_max, len(case.info.producers))


def _shift_tests(case: Case, settings: DiagnosisSettings) -> int:
    """Moved regional boxes the ranking may probe: candidates in the noise lines' count (run
    only when the budget leaves room, so not in :func:`minimum_runs`)."""
    if "regional_permeability" not in settings.kinds:
        return 0
    return len(SHIFTS) * min(settings.region_shifts, len(case.info.producers))


def budget_problem(case: Case, settings: DiagnosisSettings, given: bool,
                   where: str = "--budget") -> Problem | None:
    """A :class:`Problem` when ``settings.budget`` cannot cover :func:`minimum_runs`."""
    if settings.budget is None:
        return None
    need = minimum_runs(case, settings, given)
    if settings.budget >= need:
        return None
    dim = len(case.space.parameters)
    dated = _dated_reserve(case, settings)
    n = need - (1 if given else dim + 1) - dim - dated
    start = "1 run of the given parameters" if given else \
        f"{dim + 1} to calibrate from the deck's values"
    dated_text = f", {dated} for dated candidates" if dated else ""
    return Problem(where, f"{settings.budget} simulator calls cannot cover the minimum of "
                          f"{need} ({start}, then {n} candidate probes{dated_text} and {dim} "
                          "finite differences for the ranking)",
                   f"give {where} {need} or more, about {need + 40} to leave room for the "
                   "recalibrations, or search fewer kinds with "
                   f"{'--kinds' if where.startswith('--') else 'kinds'}")


# ============================================================================= evaluators
def local_evaluator(run_root: Path, workers: int = 2, simulator=None) -> EvaluateBatch:
    """``evaluate_batch`` running :func:`hmcore.scoring.evaluation.evaluate` on a thread pool.

    Run directories are ``run_root/<step>-<n>`` (never reused); at most ``workers`` at once.
    """
    from hmcore.scoring.evaluation import evaluate

    run_root = Path(run_root)
    counter = itertools.count()
    lock = threading.Lock()

    def evaluate_batch(case: Case, values_list: list[dict[str, float]], step: str = "run"):
        with lock:
            dirs = [run_root / f"{step}-{next(counter):05d}" for _ in values_list]
        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            return list(pool.map(lambda a: evaluate(case, a[0], a[1], simulator),
                                 zip(values_list, dirs)))

    return evaluate_batch


# ============================================================================= runs
def _ok(result) -> bool:
    status = getattr(result, "status", None)
    status = getattr(status, "value", status)
    return status != "FAIL" and getattr(result, "responses", None) is not None


@dataclass(frozen=True)
class Run:
    """A simulated point of the diagnosis: values, its residual vectors and scores."""

    values: dict[str, float]
    result: Any
    r_fit: np.ndarray | None
    r_heldout: np.ndarray | None

    @property
    def ok(self) -> bool:
        return self.r_fit is not None

    @property
    def ssr_fit(self) -> float:
        return float(self.r_fit @ self.r_fit) if self.ok else math.inf

    @property
    def ssr_heldout(self) -> float:
        return float(self.r_heldout @ self.r_heldout) if self.ok else math.inf

    @property
    def responses(self) -> pd.DataFrame | None:
        return getattr(self.result, "responses", None)


# ============================================================================= diagnosis
class Diagnosis:
    """The diagnosis of one case, step by step (see the module docstring)."""

    def __init__(self, case: Case, evaluate_batch: EvaluateBatch,
                 settings: DiagnosisSettings | None = None,
                 log: Callable[[str], None] | None = None):
        settings = settings or DiagnosisSettings()
        self.n_tests = (len(build_candidates(case.info, case.space, None, settings.kinds))
                        + _dated_reserve(case, settings) + _shift_tests(case, settings))
        self.settings = with_lines(settings, self.n_tests)
        self.obs = ObservationSet.from_case(case, self.settings.heldout_fraction)
        if case.history_end_days is None:  # score E on the same split as the residuals
            case = dataclasses.replace(case, history_end_days=self.obs.history_end_days)
        self.case = case
        self._evaluate = evaluate_batch
        self.log = log or (lambda msg: None)
        self.coords = Coordinates(case.space.parameters)
        self.n_runs = 0
        self.sim_time_s = 0.0
        self.started = time.perf_counter()
        self.timings: dict[str, float] = {}
        # state filled by the steps
        self.base: Run | None = None
        self.u_base: np.ndarray | None = None
        self.J_global: np.ndarray | None = None
        self.calibration: dict = {}
        self.residuals: dict = {}
        self.candidates: list[Candidate] = []
        self.union_case: Case | None = None
        self.scores: dict[str, Score] = {}
        self.probe_runs: dict[str, Run] = {}
        self.sensitivity: dict[str, np.ndarray] = {}
        self.ranking: dict = {}
        self.extension: dict = {}
        self.confirmed: dict[str, dict] = {}
        self.confirmed_runs: dict[str, Run] = {}
        self.recalibration: dict = {}
        self.line_search: dict[str, list[dict]] = {}
        self.held_globals: np.ndarray | None = None
        """Globals pressed against a bound at the calibrated point (set by ``rank``)."""
        self.document: dict = {}

    # ------------------------------------------------------------------ budget
    def left(self, reserve: int = 0) -> int | None:
        """Simulator calls left of the budget after ``reserve`` more (None: no budget)."""
        b = self.settings.budget
        return None if b is None else b - self.n_runs - reserve

    def _ranking_reserve(self) -> int:
        """Calls the ranking needs at most: a probe per candidate, a difference per global."""
        return (len(build_candidates(self.case.info, self.case.space, None, self.settings.kinds))
                + _dated_reserve(self.case, self.settings) + self.coords.dim)

    # ------------------------------------------------------------------ simulation
    def _run(self, case: Case, values_list: list[dict[str, float]], step: str,
             obs: ObservationSet | None = None) -> list[Run]:
        if not values_list:
            return []
        left = self.left()
        if left is not None and len(values_list) > left:  # every step checks before: a bug
            raise RuntimeError(f"{step}: {len(values_list)} simulations asked for with "
                               f"{left} of the budget {self.settings.budget} left")
        t0 = time.perf_counter()
        results = self._evaluate(case, values_list, step)
        self.n_runs += len(values_list)
        runs = []
        for values, res in zip(values_list, results):
            self.sim_time_s += float(getattr(res, "sim_time_s", 0.0) or 0.0)
            runs.append(self._rescore(Run(dict(values), res, None, None), obs))
        self.log(f"{step}: {len(values_list)} runs in {time.perf_counter() - t0:.1f} s "
                 f"({sum(r.ok for r in runs)} ok)")
        return runs

    def _rescore(self, run: Run, obs: ObservationSet | None = None) -> Run:
        """``run`` with its whitened residual vectors under ``obs`` (default: current)."""
        obs = obs or self.obs
        if not _ok(run.result):
            return Run(run.values, run.result, None, None)
        z = obs.standardized(run.result.responses)
        return Run(run.values, run.result, obs.whiten(z, "fit"), obs.whiten(z, "heldout"))

    def _scores(self, run: Run) -> dict:
        """E, per-response and per-well-response misfits, SSRs of a run."""
        s = score_responses(self.case, run.responses)
        return {"E": s["E"], "E_heldout": s["E_heldout"], "per_response": s["per_response"],
                "per_well_response": s["per_well_response"], "ssr_fit": run.ssr_fit,
                "ssr_heldout": run.ssr_heldout}

    # ------------------------------------------------------------------ 1 calibrate
    def default_start(self) -> dict[str, float]:
        """The base model as given (see :func:`hmcore.diagnosis.extensions.base_values`)."""
        return base_values(self.case.info, self.case.space)

    def calibrate(self, calibrated: dict[str, float] | None = None,
                  initial: dict[str, float] | None = None, result: Any = None) -> dict:
        """Calibrate the case's parameters (or start from ``calibrated``, e.g. a campaign's
        best: phase 1 is skipped, phase 2 still polishes it unless ``polish_given`` is off).

        Phase 1: weighted least squares (sigma from the data or estimated from the observed
        series, no time correlation) from ``initial`` (default: the base model as given).
        Then the noise level and its time correlation are re-estimated from the residuals of
        the phase-1 model, and phase 2 polishes the fit under that noise model (fresh
        finite-difference Jacobian, prewhitened residuals).

        With a budget, the ranking's calls are set aside first; a budget that cannot cover
        :func:`minimum_runs` is refused (ValueError) before any simulation. ``result``: the
        simulation of ``calibrated`` when it was already made (a second round starts from the
        first's recalibrated model), so it is not run again."""
        t0 = time.perf_counter()
        space = self.case.space
        problem = budget_problem(self.case, self.settings, calibrated is not None, "budget")
        if problem:
            raise ValueError(str(problem))
        reserve = self._ranking_reserve() if self.settings.budget is not None else 0
        obs0 = self.obs
        phases = []
        if calibrated is not None:
            missing = [n for n in space.names if n not in calibrated]
            if missing:
                raise KeyError(f"calibrated values miss parameters {missing}")
            values = {n: float(calibrated[n]) for n in space.names}
            run = (self._rescore(Run(values, result, None, None)) if result is not None
                   else self._run(self.case, [values], "calibration")[0])
            if not run.ok:
                raise RuntimeError(f"the calibrated model failed to simulate: "
                                   f"{getattr(run.result, 'reason', '')}")
            phases.append({"phase": "given", "runs": 0 if result is not None else 1})
        else:
            start = {**self.default_start(), **(initial or {})}
            wls = obs0.without_time_correlation()
            lm = self._minimise(LevenbergMarquardt(self.coords.to_u(start),
                                                   self._capped(self.settings.calibration, 0.3),
                                                   label="phase 1"), wls, reserve)
            run = lm.best.payload
            phases.append(self._lm_doc("1: weighted least squares, noise from the observed "
                                       "series", lm, start))
        # the noise model from the residuals of the calibrated model
        self.obs = obs0.refine(run.responses, self.case.observed)
        run = self._rescore(run)
        u = self.coords.to_u(run.values)
        left = self.left(reserve)
        if (calibrated is None or self.settings.polish_given) and \
                (left is None or left >= self.coords.dim + 1):
            lm = self._minimise(LevenbergMarquardt(u, self._capped(self.settings.polish, 0.15),
                                                   start=Point(u, run.r_fit, run),
                                                   label="phase 2"), self.obs, reserve)
            run, u = lm.best.payload, lm.best.u
            near = self.settings.reuse_jacobian_within
            if lm.J_fd is not None and np.max(np.abs(lm.u_fd - u)) <= near:
                self.J_global = lm.J_fd  # close enough to the final point: no new differences
            phases.append(self._lm_doc("2: prewhitened residuals, noise from the residuals",
                                       lm, None))
        elif calibrated is None or self.settings.polish_given:
            phases.append({"phase": "2: skipped, the budget is kept for the ranking", "runs": 0})
        self.base, self.u_base = run, u
        lm_doc = {"method": ("levenberg-marquardt" if calibrated is None else
                             "given, polished" if self.settings.polish_given else "given"),
                  "runs": sum(p["runs"] for p in phases), "phases": phases,
                  "noise_initial": obs0.noise_report, "noise": self.obs.noise_report}
        sc = self._scores(self.base)
        self.calibration = {"values": self.base.values, "u": self.u_base.tolist(), **lm_doc,
                            **sc, "parameters": [p.model_dump(mode="json")
                                                 for p in space.parameters],
                            "n_fit": self.obs.n_fit, "n_heldout": self.obs.n_heldout,
                            "history_end_days": self.obs.history_end_days}
        self.timings["calibrate"] = time.perf_counter() - t0
        self.log(f"calibrated: E = {sc['E']:.5g}, held-back E = {sc['E_heldout']:.5g}, "
                 f"SSR fit {sc['ssr_fit']:.1f} over {self.obs.n_fit} points")
        return self.calibration

    def _capped(self, lm: LMSettings, share: float) -> LMSettings:
        """``lm`` with its evaluations capped to ``share`` of the budget (when one is set)."""
        if self.settings.budget is None:
            return lm
        cap = max(self.coords.dim + 3, int(share * self.settings.budget))
        return dataclasses.replace(lm, max_evaluations=min(lm.max_evaluations, cap))

    def _minimise(self, lm: LevenbergMarquardt, obs: ObservationSet,
                  reserve: int) -> LevenbergMarquardt:
        def evaluate(batch):
            runs = self._run(self.case, [self.coords.to_values(u) for _, u in batch],
                             "calibration", obs)
            return [(run.r_fit, run) for run in runs]

        run_lockstep([lm], evaluate, limit=self.left(reserve))
        if lm.best is None:
            raise RuntimeError(f"calibration failed: {lm.reason}")
        return lm

    @staticmethod
    def _lm_doc(phase: str, lm: LevenbergMarquardt, start: dict | None) -> dict:
        return {"phase": phase, "runs": lm.n_evaluations, "iterations": lm.iteration,
                "stopped": lm.reason, "start": start, "ssr": lm.best.ssr,
                "history": [dataclasses.asdict(h) for h in lm.history]}

    # ------------------------------------------------------------------ 2 analyse
    def analyse(self) -> dict:
        t0 = time.perf_counter()
        self.residuals = analyse_residuals(self.obs, self.base.responses)
        self.timings["analyse"] = time.perf_counter() - t0
        self.log(f"residuals: {len(self.residuals['flags'])} findings beyond noise")
        return self.residuals

    # ------------------------------------------------------------------ 3 rank
    def rank(self) -> dict:
        t0 = time.perf_counter()
        s = self.settings
        values0 = self.base.values
        self.candidates = build_candidates(self.case.info, self.case.space, values0, s.kinds)
        self.union_case = self.case.with_space(extended_space(self.case.space, self.candidates))
        jobs = screening.probe_jobs(self.coords, self.u_base, values0, self.candidates,
                                    self.J_global is None, s.global_fd_step)
        left = self.left()
        if left is not None and len(jobs) > left:  # set aside by the calibration: a bug
            raise ValueError(f"budget {s.budget} leaves {left} simulator calls after the "
                             f"calibration, but the ranking needs {len(jobs)}")
        runs = self._run(self.union_case, [j.values for j in jobs], "ranking")
        r0 = self.base.r_fit
        residuals = [run.r_fit for run in runs]
        if self.J_global is None:
            self.J_global = screening.global_jacobian(r0, jobs, residuals, self.coords.dim)
        self.held_globals = screening.held_at_bounds(self.J_global, r0, self.u_base)
        result = screening.screen(self.candidates, jobs, residuals,
                                  [getattr(run.result, "reason", "") for run in runs], r0,
                                  self.J_global, self.held_globals, self.coords.names, s)
        datings, dated = self._date(result, r0)
        shifted = self._shifted(result, len(dated))
        for added, step in ((dated, "dating"), (shifted, "region-shifts")):
            if not added:  # their probes, then the ranking of them all
                continue
            self.candidates = self.candidates + added
            self.union_case = self.case.with_space(extended_space(self.case.space,
                                                                  self.candidates))
            more = screening.probe_jobs(self.coords, self.u_base, values0, added, False,
                                        s.global_fd_step)
            jobs, runs = jobs + more, runs + self._run(self.union_case,
                                                       [j.values for j in more], step)
        if dated or shifted:
            residuals = [run.r_fit for run in runs]
            result = screening.screen(self.candidates, jobs, residuals,
                                      [getattr(run.result, "reason", "") for run in runs], r0,
                                      self.J_global, self.held_globals, self.coords.names, s)
        self.probe_runs = {j.candidate.id: run for j, run in zip(jobs, runs) if j.candidate}
        result.document["dating"] = [d.to_dict() for d in datings]
        self.scores, self.sensitivity, self.ranking = (result.scores, result.sensitivity,
                                                       result.document)
        self.timings["rank"] = time.perf_counter() - t0
        order, beyond = self.ranking["order"], self.ranking["beyond_noise"]
        top = ", ".join(f"{k} ({self.scores[k].chi2:.0f})" for k in order[:5])
        self.log(f"ranking: {len(beyond)} of {len(order)} candidates beyond noise "
                 f"({len(self.ranking['screened'])} screened for recalibration); top: {top}")
        return self.ranking

    def _shifted(self, result: screening.Screening, reserved: int) -> list[Candidate]:
        """The moved boxes of the strongest regional candidates beyond noise (at most
        ``settings.region_shifts`` wells, the strongest first), as many wells' as the budget
        leaves room for besides ``reserved`` other probes and a first step of the
        recalibration (a finite difference per parameter for ``confirm_top`` candidates)."""
        s = self.settings
        if "regional_permeability" not in s.kinds or s.region_shifts < 1:
            return []
        by_id = {c.id: c for c in self.candidates}
        regional = [k for k in result.document["beyond_noise"]
                    if by_id[k].kind == "regional_permeability" and "shift" not in
                    by_id[k].details][: s.region_shifts]
        taken = [tuple(c.parameter.box) for c in self.candidates
                 if c.kind == "regional_permeability" and c.parameter.box]
        left = self.left(reserved + s.confirm_top * (self.coords.dim + 2))
        out: list[Candidate] = []
        for k in regional:
            moved = [c for c in shifted_regions(self.case.info, by_id[k].wells[0], taken)
                     if c.name not in self.case.space.names]
            if left is not None and len(out) + len(moved) > left:
                self.log(f"ranking: the moved boxes beside {by_id[k].wells[0]} not probed: "
                         f"{len(moved)} runs, {max(left - len(out), 0)} left of the budget "
                         "after the recalibration's first step")
                break
            taken += [tuple(c.parameter.box) for c in moved]
            out += moved
        if out:
            self.log(f"ranking: {len(out)} moved boxes beside "
                     f"{', '.join(sorted({c.wells[0] for c in out}, key=natural_key))}")
        return out

    def _date(self, result: screening.Screening, r0: np.ndarray
              ) -> tuple[list[dating.Dating], list[Candidate]]:
        """The date scans of the wells (``productivity_change``), from their well-skin
        probes, and the dated candidates they justify (:mod:`hmcore.diagnosis.dating`)."""
        s = self.settings
        if "productivity_change" not in s.kinds:
            return [], []
        idx = self.obs.vector_index("fit")
        days = self.obs.rows.days.to_numpy(float)[idx]
        wells = self.obs.rows.well.to_numpy()[idx]
        Q = projector_basis(self.J_global[:, ~self.held_globals])
        scans = {}
        for well in sorted(self.case.info.producers, key=natural_key):
            j = result.sensitivity.get(f"well_skin:{well}")
            if j is not None:
                scans[well] = (j, dating.scan_days(self.case.info.report_days, days,
                                                   wells == well, s.dating_min_after))
        n_tests = sum(len(d) for _, d in scans.values())
        datings = [dating.date_well(w, r0, j, days, Q, tried, s.dating_alpha, n_tests)
                   for w, (j, tried) in scans.items()]
        chosen = dating.choose(datings, s.dated_max)
        if datings:
            self.log("dating: " + ", ".join(
                f"{d.well} day {d.day:g} (+{d.gain:.0f} vs {d.threshold:.1f})"
                for d in sorted(datings, key=lambda d: -d.gain)[:3]))
        dated = [dated_productivity(self.case.info, d.well, d.day) for d in chosen]
        return datings, [c for c in dated if c.name not in self.case.space.names]

    # ------------------------------------------------------------------ 4 extend
    def extend(self) -> dict:
        """The extended models of the leading candidates (no simulation)."""
        by_id = {c.id: c for c in self.candidates}
        screened, per_well = [], {}
        for k in self.ranking["screened"]:  # best first; a well's boxes are near-alternatives:
            c = by_id[k]  # its best two go on, so that they do not fill every slot
            if c.kind == "regional_permeability":
                per_well[c.wells] = per_well.get(c.wells, 0) + 1
                if per_well[c.wells] > REGIONS_PER_WELL:
                    continue
            screened.append(k)
        top = screening.confirm_choice([(k, self.scores[k].chi2) for k in screened],
                                       self.settings)
        models = []
        for cid in top:
            c = by_id[cid]
            space = extended_space(self.case.space, [c])
            models.append({"id": cid, "kind": c.kind, "description": c.description,
                           "parameters": [p.model_dump(mode="json") for p in space.parameters],
                           "start": {**self.base.values, c.name: c.neutral},
                           "predicted_value": next(r["predicted_value"]
                                                   for r in self.ranking["candidates"]
                                                   if r["id"] == cid)})
        self.extension = {"models": models,
                          "note": ("no candidate explains more than noise: nothing to extend"
                                   if not models else
                                   f"{len(models)} leading candidate(s) to recalibrate")}
        return self.extension

    # ------------------------------------------------------------------ 5 recalibrate
    def recalibrate(self) -> dict:
        t0 = time.perf_counter()
        s = self.settings
        by_id = {c.id: c for c in self.candidates}
        ids = [m["id"] for m in self.extension.get("models", [])]
        starts = self._line_search(ids)
        lm_settings = s.recalibration
        if s.budget is not None and ids:
            lm_settings = refit.capped(lm_settings, self.left() // len(ids))
        minimisers, coords = [], []
        for cid in ids:
            c = by_id[cid]
            u0, run0 = starts[cid]
            J0 = np.column_stack([self.J_global, self.sensitivity[cid]])
            minimisers.append(LevenbergMarquardt(u0, lm_settings,
                                                 start=Point(u0.copy(), run0.r_fit, run0),
                                                 jacobian=J0, label=cid))
            coords.append(Coordinates(extended_space(self.case.space, [c]).parameters))

        def evaluate(batch):
            values = [coords[k].to_values(u) for k, u in batch]
            runs = self._run(self.union_case, values, "recalibration")
            return [(run.r_fit, run) for run in runs]

        run_lockstep(minimisers, evaluate, s.workers, limit=self.left())
        # the contenders (best fits, each beyond noise) continue from a fresh finite-difference
        # Jacobian: Broyden's updates stall in the curved valleys the globals make
        contenders = sorted((k for k, m in enumerate(minimisers) if m.best is not None
                             and self.base.ssr_fit - m.best.ssr > s.fit_threshold),
                            key=lambda k: minimisers[k].best.ssr)[: s.refine_top]
        refine_settings = s.refine
        if s.budget is not None and contenders:
            left = self.left() // len(contenders)
            refine_settings = refit.capped(refine_settings, left)
            contenders = contenders if left > len(self.coords.names) + 1 else []
        refined = {k: LevenbergMarquardt(minimisers[k].best.u, refine_settings,
                                         start=minimisers[k].best, label=f"{ids[k]} (refined)")
                   for k in contenders}
        if refined:
            keys = list(refined)

            def evaluate_refined(batch):
                return evaluate([(keys[j], u) for j, u in batch])

            run_lockstep([refined[k] for k in keys], evaluate_refined, s.workers,
                         limit=self.left())
        restarts = self._restart(ids, minimisers, refined, coords)
        base_sc = self._scores(self.base)
        self.confirmed, self.confirmed_runs = {}, {}
        for k, (cid, lm) in enumerate(zip(ids, minimisers)):
            self.confirmed[cid], self.confirmed_runs[cid] = self._record(
                cid, k, lm, refined.get(k), restarts.get(cid, {}), starts[cid][1], base_sc)
        self.recalibration = {"confirmed": self.confirmed, "thresholds": {
            "fit": s.fit_threshold, "fit_dated": decision.fit_line(s, 2),
            "heldout": s.heldout_threshold}}
        self.timings["recalibrate"] = time.perf_counter() - t0
        return self.recalibration

    def _record(self, cid: str, k: int, lm: LevenbergMarquardt,
                refined: LevenbergMarquardt | None, restart: dict, start: Run,
                base_sc: dict) -> tuple[dict, Run]:
        """The recalibration record of candidate ``cid`` (its best of the warm start, the
        refinement and an accepted restart) and its best run."""
        s = self.settings
        c = next(x for x in self.candidates if x.id == cid)
        history = [dataclasses.asdict(h) for h in lm.history]
        n_eval, reason, iters = lm.n_evaluations, lm.reason, lm.iteration
        n_eval += restart.get("runs", 0)
        for label, r in (("refined", refined),
                         ("restart (SSR + prior)", restart.get("minimiser")
                          if restart.get("accepted") else None)):
            if r is None:
                continue
            n_eval += r.n_evaluations if label == "refined" else 0
            history += [{**dataclasses.asdict(h), "note": f"{label} {h.note}".strip()}
                        for h in r.history]
            # an accepted restart replaces the warm start (see _restart), a refinement
            # when it fits better
            if r.best is not None and (label != "refined" or
                                       r.best.payload.ssr_fit <= lm.best.payload.ssr_fit):
                reason, iters, lm = r.reason, iters + r.iteration, r
        run = lm.best.payload
        sc = self._scores(run) if run is not self.base else base_sc
        d_fit = base_sc["ssr_fit"] - sc["ssr_fit"]
        d_ho = base_sc["ssr_heldout"] - sc["ssr_heldout"]
        e_ho_b, e_ho_a = base_sc["E_heldout"], sc["E_heldout"]
        line = decision.fit_line(s, 2 if c.details.get("start_day") is not None else 1)
        fit_ok = d_fit > line
        ho_ok, quiet = decision.heldout_confirms(base_sc["ssr_heldout"], sc["ssr_heldout"],
                                                 e_ho_b, e_ho_a, self.obs.n_noise("heldout"), s)
        value = run.values.get(c.name, c.neutral)
        record = {
            "start_value": start.values.get(c.name, c.neutral),
            "line_search": self.line_search.get(cid, []),
            "id": cid, "values": {c.name: c.neutral, **run.values},
            "value": value,
            "runs": n_eval, "iterations": iters, "stopped": reason, "refined": refined is not None,
            "restart": {key: v for key, v in restart.items() if key != "minimiser"} or None,
            "ssr_fit_before": base_sc["ssr_fit"], "ssr_fit_after": sc["ssr_fit"],
            "ssr_heldout_before": base_sc["ssr_heldout"], "ssr_heldout_after": sc["ssr_heldout"],
            "delta_ssr_fit": d_fit, "delta_ssr_heldout": d_ho,
            "fit_before": base_sc["E"], "fit_after": sc["E"],
            "heldout_before": e_ho_b, "heldout_after": e_ho_a,
            "fit_line": line, "fit_beyond_noise": bool(fit_ok),
            "heldout_beyond_noise": bool(ho_ok), "open_end": open_end(c, value, s.open_end),
            "heldout_within_noise_before": bool(quiet),
            "per_well_response_after": sc["per_well_response"],
            "per_well_response_heldout_after": decision.per_well_heldout(self.case,
                                                                         run.responses),
            "history": history}
        self.log(f"recalibrated {cid}: SSR fit {base_sc['ssr_fit']:.1f} -> "
                 f"{sc['ssr_fit']:.1f}, held-back {base_sc['ssr_heldout']:.1f} -> "
                 f"{sc['ssr_heldout']:.1f}; E {base_sc['E']:.4g} -> {sc['E']:.4g}, "
                 f"held-back E {e_ho_b:.4g} -> {e_ho_a:.4g}")
        return record, run

    def _restart(self, ids: list[str], minimisers: list[LevenbergMarquardt],
                 refined: dict[int, LevenbergMarquardt],
                 coords: list[Coordinates]) -> dict[str, dict]:
        """Recalibrate the best candidates (:func:`refit.restart_choice`) again from the base
        model as given, when the calibration left global parameters at (within ``near_bound``
        of) their bounds; otherwise (``restart_on_veto``) the best fits that the held-back
        history vetoes (:func:`refit.veto_restart_choice`).

        A global at its bound has absorbed what it could of a missing effect; with the right
        extension its best value is usually back inside, but the warm-started recalibration
        starts in the absorbed basin and its linear model points along the bound. A fit that
        the held-back history vetoes has often stayed in such a basin without a bound. The
        restart puts the globals at the deck's values, tries the candidate alone there
        (``restart_grid`` and its recalibrated value: does the extension alone explain the data
        on the model as given?) and from the best of those minimises the fitted SSR plus a
        prior on the globals (``restart_prior_sd``), fresh finite-difference Jacobian.

        Its result replaces the warm start's only when (a) its SSR + prior is lower than the
        warm start's and its fitted SSR at most ``restart_slack`` higher (of fits the data
        cannot tell apart, the one closer to the model as given), and (b) the restart's globals
        with the candidate neutral fit worse than the calibrated base model (otherwise the
        calibration, not the candidate, was short of its minimum, and the gain would be the
        globals'; a well's own skin is neutral at the global skin of the restart's point).
        Returns, per restarted candidate id, its record (``minimiser``, ``runs``,
        ``grid``, ``ssr_fit``, ``prior``, ``ssr_fit_warm``, ``prior_warm``, ``accepted``,
        ``reason``, ...)."""
        s = self.settings
        at_bound = [n for n, u in zip(self.coords.names, self.u_base)
                    if abs(u) >= 1.0 - s.near_bound]
        if not ids or (not at_bound and not s.restart_on_veto):
            return {}
        by_id = {c.id: c for c in self.candidates}
        warm = {k: min([x.best for x in (m, refined.get(k)) if x is not None and x.best is not None],
                       key=lambda b: b.ssr, default=None) for k, m in enumerate(minimisers)}
        warm_ssr = {k: w.ssr for k, w in warm.items() if w is not None}
        if at_bound:
            chosen = refit.restart_choice(warm_ssr, self.base.ssr_fit, s)
            trigger = f"globals {at_bound} were at their bounds"
        else:
            base_sc = self._scores(self.base)
            n_ho = self.obs.n_noise("heldout")

            def confirms(k: int) -> bool:
                run = warm[k].payload
                # plainly (E and SSR both drop): a fit whose held-back E rises is restarted
                # even when its SSR drops decisively (PUNQ-S3, aquifer 2 x9.2: warm start +25 %
                # held-back E, the restart +13 %, the truth +11 %)
                return decision.heldout_confirms(base_sc["ssr_heldout"], run.ssr_heldout,
                                                 base_sc["E_heldout"],
                                                 self._scores(run)["E_heldout"], n_ho, s,
                                                 decisive=False)[0]

            chosen = refit.veto_restart_choice(warm_ssr, {k: confirms(k) for k in warm_ssr},
                                               self.base.ssr_fit, s)
            trigger = ("the best fit(s) " + ", ".join(ids[k] for k in chosen)
                       + " do not plainly predict the held-back history better than the "
                         "calibrated model (held-back E and SSR both lower)")
        if not chosen:
            return {}
        start_globals = self.coords.to_u(self.default_start())
        settings = s.restart
        if s.budget is not None:
            per = refit.restart_evaluations(self.left(), len(chosen), len(s.restart_grid),
                                            self.coords.dim)
            if per is None:
                self.log(f"restart skipped: {self.left()} simulator calls left")
                return {}
            settings = refit.capped(settings, per)
        self.log(f"restart from the deck's values: {trigger}")
        # the candidate alone on the model as given: a grid over its range (and its
        # recalibrated value); the best point starts the restart
        jobs, tags = [], []
        for k in chosen:
            m = minimisers[k]
            for g in refit.restart_grid(s.restart_grid,
                                        float(m.best.u[-1]) if m.best is not None else None):
                u = np.concatenate([start_globals, [g]])
                jobs.append(coords[k].to_values(u))
                tags.append((k, u))
        grid_runs = self._run(self.union_case, jobs, "restart-grid")
        grid_best: dict[int, Any] = {}
        for (k, u), run in zip(tags, grid_runs):
            if run.ok and (k not in grid_best or run.ssr_fit < grid_best[k].ssr):
                grid_best[k] = Point(u, run.r_fit, run)
        prior = refit.GlobalsPrior(start_globals, s.restart_prior_sd)
        for k, p in grid_best.items():
            grid_best[k] = Point(p.u, prior.extend(p.u, p.r), p.payload)
        restarts = {k: LevenbergMarquardt(grid_best[k].u if k in grid_best else
                                          np.concatenate([start_globals, [0.0]]), settings,
                                          start=grid_best.get(k), label=f"{ids[k]} (restart)")
                    for k in chosen}

        def evaluate(batch):
            runs = self._run(self.union_case, [coords[k].to_values(u) for k, u in batch],
                             "restart")
            return [(prior.extend(u, run.r_fit), run) for (_, u), run in zip(batch, runs)]

        order = list(restarts)
        run_lockstep([restarts[k] for k in order],
                     lambda batch: evaluate([(order[j], u) for j, u in batch]), s.workers,
                     limit=self.left(len(chosen)))  # one check run each kept back
        out: dict[str, dict] = {}
        checks = []
        for k, r in restarts.items():
            cid, w = ids[k], warm[k]
            grid = [{"value": run.values[by_id[cid].name], "ssr_fit": run.ssr_fit}
                    for (j, _), run in zip(tags, grid_runs) if j == k]
            rec = {"minimiser": r, "runs": r.n_evaluations + len(grid), "grid": grid,
                   "globals_at_bounds": at_bound, "trigger": trigger, "ssr_fit_warm": w.ssr,
                   "prior_warm": prior.value(w.u), "accepted": False}
            if r.best is not None:
                run = r.best.payload
                rec.update({"ssr_fit": run.ssr_fit, "ssr_heldout": run.ssr_heldout,
                            "prior": prior.value(r.best.u), "values": run.values})
            if r.best is None or run.ssr_fit > w.ssr + s.restart_slack or \
                    run.ssr_fit + rec["prior"] >= w.ssr + rec["prior_warm"]:
                rec["reason"] = ("no better than the warm-started recalibration (fitted SSR, "
                                 "or SSR + prior on the globals)")
            else:
                c = by_id[cid]
                neutral = dict(r.best.payload.values)
                neutral[c.name] = (current_skin(c.wells[0], self.case.space, neutral,
                                                self.case.info)
                                   if c.kind == "well_skin" else c.neutral)
                checks.append((cid, neutral))
            out[cid] = rec
        for (cid, _), run in zip(checks, self._run(self.union_case, [v for _, v in checks],
                                                   "restart-check")):
            rec = out[cid]
            rec["runs"] += 1
            rec["ssr_fit_neutral"] = run.ssr_fit
            rec["accepted"] = bool(run.ok and run.ssr_fit >= self.base.ssr_fit)
            rec["reason"] = ("as good a fit as the warm start or better, closer to the deck's "
                             "values, and only with the candidate" if rec["accepted"] else
                             "rejected: the restart's globals fit better than the calibration "
                             "even with the candidate neutral (the gain would be the globals')")
            self.log(f"restart {cid}: SSR fit {rec['ssr_fit']:.1f} + prior {rec['prior']:.1f} "
                     f"(warm {rec['ssr_fit_warm']:.1f} + {rec['prior_warm']:.1f},"
                     f" candidate neutral {run.ssr_fit:.1f}, base {self.base.ssr_fit:.1f}): "
                     f"{'accepted' if rec['accepted'] else 'rejected'}")
        return out

    def _line_search(self, ids: list[str]) -> dict[str, tuple[np.ndarray, Run]]:
        """Start points of the recalibrations (scaled coordinates: globals + the candidate).

        For each candidate, the best of the calibrated model, its probe run, and runs at 1/2,
        1 and 3/2 of the score test's linear step along the joint direction the linear model
        gives (:func:`refit.joint_direction`: the candidate moves, the free globals undo what
        they had absorbed of it). A response that bends (an aquifer's strength, a baffle, a
        layer that stops flowing) can put that step out of reach of a warm-started LM whose
        first steps trust the linear model only near the start."""
        s = self.settings
        by_id = {c.id: c for c in self.candidates}
        self.line_search = {}
        starts: dict[str, tuple[np.ndarray, Run]] = {}
        jobs, tags = [], []
        free = ~self.held_globals
        for cid in ids:
            c = by_id[cid]
            cc = Coordinates([c.parameter])
            u0 = float(cc.to_u({c.name: c.neutral})[0])
            u_probe = float(cc.to_u({c.name: c.probe})[0])
            base_u = np.concatenate([self.u_base, [u0]])
            points = [(base_u, self.base),
                      (np.concatenate([self.u_base, [u_probe]]), self.probe_runs.get(cid))]
            starts[cid] = min(((u, r) for u, r in points if r is not None and r.ok),
                              key=lambda ur: ur[1].ssr_fit)
            direction = refit.joint_direction(self.J_global, free, self.sensitivity[cid])
            co = Coordinates(extended_space(self.case.space, [c]).parameters)
            for u in refit.line_search_points(base_u, self.scores[cid].step_u, direction,
                                              s.line_search, [u for u, _ in points]):
                jobs.append(co.to_values(u))
                tags.append((cid, u))
        if not refit.line_search_affordable(self.left(), len(jobs), len(ids), self.coords.dim):
            return starts
        for (cid, u), run in zip(tags, self._run(self.union_case, jobs, "line-search")):
            c = by_id[cid]
            self.line_search.setdefault(cid, []).append(
                {"value": run.values[c.name], "ssr_fit": run.ssr_fit,
                 "globals": {n: run.values[n] for n in self.coords.names}})
            if run.ok and run.ssr_fit < starts[cid][1].ssr_fit:
                starts[cid] = (u, run)
        return starts

    # ------------------------------------------------------------------ 6 decide
    def decide(self) -> dict:
        """The ranked causes, the selected extension (or null), the gain: the document."""
        base_sc = self._scores(self.base)
        base_ho = decision.per_well_heldout(self.case, self.base.responses)
        d = decision.decide(
            self.candidates, self.scores, self.confirmed, self.ranking, base_sc, base_ho,
            self.obs.n_noise("heldout"),
            {"n_fit": self.obs.n_fit, "n_heldout": self.obs.n_heldout,
             "n_fit_measured": self.obs.n_noise("fit"),
             "n_heldout_measured": self.obs.n_noise("heldout")},
            self.obs.history_end_days, self.settings, self.residuals)
        shown = d.shown
        per_well = decision.per_well_table(
            base_sc["per_well_response"], base_ho,
            self.confirmed[shown]["per_well_response_after"] if shown else None,
            self.confirmed[shown]["per_well_response_heldout_after"] if shown else None)
        by_id = {c.id: c for c in self.candidates}
        selected = None
        if d.selected is not None:
            sel = d.selected
            selected = {**decision.cause(by_id[sel], self.scores.get(sel), self.confirmed.get(sel),
                                         "selected"),
                        "values": self.confirmed[sel]["values"]}
        self.document = {
            "case": self.case.name, "source": str(self.case.source),
            "history_end_days": self.obs.history_end_days,
            "parameters": self.case.space.names,
            "calibrated": self.base.values,
            "causes": d.causes,
            "selected": selected,
            "accepted": ([decision.accepted_cause(selected, self.confirmed[d.selected], 1)]
                         if selected else []),
            "fits_beyond_noise": list(d.fits),
            "statistic": decision.statistic(
                self.confirmed, d.fits, self.base.ssr_fit, self.n_tests, self.settings,
                {c.id for c in self.candidates if c.details.get("start_day") is not None},
                self.obs.n_noise("fit")),
            "verdict": d.verdict,
            "heldout_within_noise": d.heldout_quiet,
            "gain": d.gain,
            "per_well_response": {"extension": shown, "rows": per_well},
            "candidates_recalibrated": self.confirmed,
            "residuals": self.residuals,
            "ranking": self.ranking,
            "calibration": self.calibration,
            "settings": self.settings.to_dict(),
            "cost": {"simulations": self.n_runs, "sim_time_s": self.sim_time_s,
                     "wall_time_s": time.perf_counter() - self.started, "steps_s": self.timings},
        }
        st = self.document["statistic"]
        share = st and st["vs_none"]["share"]
        if selected and st["cause"] == d.selected and share is not None and \
                share < self.settings.partial_share:
            self.document["verdict"] += (
                f" ({d.selected} removes only {100 * share:.0f} % of the fitted misfit beyond "
                "noise: something else acts too)")
        return self.document

    # ------------------------------------------------------------------ 7 report
    def report(self, out_dir: Path | None = None, doc: dict | None = None,
               extended: Run | None = None) -> dict:
        """Write diagnosis.json, report.md and the residual plots into ``out_dir``: this
        round's document, or ``doc`` (two rounds combined) with ``extended`` the run plotted
        against the calibrated model."""
        from hmcore.diagnosis.report import markdown_report, plot_wells
        from storage.jsonable import to_jsonable

        doc = doc or self.document or self.decide()
        files: dict[str, Any] = {}
        if out_dir is not None:
            out_dir = Path(out_dir)
            out_dir.mkdir(parents=True, exist_ok=True)
            plots = []
            if self.settings.plots:
                shown = doc["per_well_response"]["extension"]
                ext = extended if extended is not None else \
                    (self.confirmed_runs.get(shown) if shown else None)
                plots = plot_wells(self.obs, self.base.responses,
                                   ext.responses if ext is not None else None,
                                   _plot_wells(doc, self.case), out_dir, label=shown or "")
            doc["plots"] = [p.name for p in plots]
            (out_dir / "diagnosis.json").write_text(
                json.dumps(to_jsonable(doc, "diagnosis.json"), indent=2))
            (out_dir / "report.md").write_text(markdown_report(doc))
            files = {"diagnosis": out_dir / "diagnosis.json", "report": out_dir / "report.md",
                     "plots": plots}
        return files


def _plot_wells(doc: dict, case: Case) -> list[str]:
    """The wells the answer names: the first cause's and, when it is `unexplained` (or a
    partial answer led by it), the accepted causes' too; every well when they name none."""
    wells: list[str] = []
    for c in doc["causes"]:
        if c["kind"] != "none":
            wells += list(c["wells"])
            break
    for a in doc.get("accepted") or []:
        wells += list(a.get("wells") or [])
    return (sorted(set(wells), key=natural_key) if wells
            else sorted(case.info.wells, key=natural_key))
