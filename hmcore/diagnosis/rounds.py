"""A whole diagnosis: the rounds of one fitted window and, when it ends without an answer,
a later window.

1. Round 1 on the case's fitted window (:class:`hmcore.diagnosis.workflow.Diagnosis`: calibrate,
   analyse, rank, extend, recalibrate, decide);
2. round 2 with round 1's cause in the model, for a second cause
   (:mod:`hmcore.diagnosis.forward`);
3. when nothing was accepted and the calibrated model misses the held-back history beyond
   noise, the same on a later fitted window, and on the next while none names a cause
   (:mod:`hmcore.diagnosis.origins`: a rolling origin).

Every step calls ``on_step(name, diagnosis)`` as it ends (``calibration``, ``residuals``,
``ranking``, ``extension``, ``recalibration``; round 2's prefixed ``2-``, the second
window's ``later-``, the third's ``later3-``, ...), so that the Prefect flow stores each as
an artifact. Every simulation of every round counts against the one budget. Nothing here
simulates: ``evaluate_batch`` is injected.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from hmcore.model.case import Case
from hmcore.diagnosis import forward, origins
from hmcore.diagnosis.budget import budget_problem
from hmcore.diagnosis.runs import EvaluateBatch, Run
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.diagnosis.workflow import Diagnosis

OnStep = Callable[[str, Diagnosis], None]
STEP_NAMES = ("calibration", "residuals", "ranking", "extension", "recalibration")


@dataclass(frozen=True)
class Outcome:
    """The diagnosis document, the :class:`Diagnosis` whose window gave the answer (its
    noise model and calibrated run draw the plots) and the run of the final model (None:
    that diagnosis's shown candidate)."""

    document: dict
    diagnosis: Diagnosis
    final: Run | None

    def report(self, out_dir: Path | None) -> dict:
        return self.diagnosis.report(out_dir, self.document, self.final)


def run_round(d: Diagnosis, calibrate: Callable[[], Any], on_step: OnStep,
              prefix: str = "") -> dict:
    """The steps of one round, ``on_step`` after each; returns the round's decision."""
    calibrate()
    on_step(f"{prefix}calibration", d)
    for name, step in zip(STEP_NAMES[1:], (d.analyse, d.rank, d.extend, d.recalibrate)):
        step()
        on_step(f"{prefix}{name}", d)
    return d.decide()


def diagnose_window(case: Case, evaluate_batch: EvaluateBatch, settings: DiagnosisSettings,
                    calibrated: dict | None, initial: dict | None, log: Callable[[str], None],
                    on_step: OnStep, prefix: str = "") -> Outcome:
    """Round 1 and, when it finds a cause, round 2 on ``case``'s fitted window."""
    d = Diagnosis(case, evaluate_batch, settings, log)
    doc = run_round(d, lambda: d.calibrate(calibrated, initial), on_step, prefix)
    p = forward.plan(d, doc)
    if isinstance(p, str):
        doc["rounds"], doc["no_second_round"] = [], p
        return Outcome(_incomplete(doc, d), d, None)
    try:
        doc2 = run_round(p.diagnosis, lambda: forward.start_round(p, d), on_step,
                         f"{prefix}2-")
    except RuntimeError as exc:  # e.g. a calibration that failed: round 1's answer stands
        doc["rounds"], doc["no_second_round"] = [], f"round 2 failed: {exc}"
        return Outcome(_incomplete(doc, d), d, None)
    doc, final = forward.combine(d, doc, p, doc2)
    return Outcome(doc, d, final)


def _incomplete(doc: dict, d: Diagnosis) -> dict:
    """Round 1's answer without a round 2: the verdict says when its selected cause still
    leaves the held-back history beyond noise (:func:`forward.remaining_text`)."""
    sel = doc.get("selected")
    if sel and sel["id"] in d.confirmed:
        doc["verdict"] += forward.remaining_text(d.confirmed[sel["id"]]["ssr_heldout_after"],
                                                 d.obs.n_noise("heldout"), d.settings,
                                                 sel["id"])
    return doc


def diagnose_all(case: Case, evaluate_batch: EvaluateBatch, *, calibrated: dict | None = None,
                 initial: dict | None = None, settings: DiagnosisSettings | None = None,
                 log: Callable[[str], None] | None = None,
                 on_step: OnStep | None = None) -> Outcome:
    """Every window and round (see the module docstring); the document's ``cost`` counts
    the simulations of all of them."""
    s = settings or DiagnosisSettings()
    log = log or (lambda msg: None)
    on_step = on_step or (lambda name, d: None)
    started = time.perf_counter()
    count = {"runs": 0, "sim_time_s": 0.0}

    def counted(c, values_list, step):
        results = evaluate_batch(c, values_list, step)
        count["runs"] += len(values_list)
        count["sim_time_s"] += sum(float(getattr(r, "sim_time_s", 0.0) or 0.0)
                                   for r in results)
        return results

    out = last = diagnose_window(case, counted, s, calibrated, initial, log, on_step)
    docs = [out.document]
    while True:  # a rolling origin: later windows in time order, until one names a cause
        origin = origins.later_origin(last.diagnosis.case, last.document, s)
        left = None if s.budget is None else s.budget - count["runs"]
        if isinstance(origin, float) and left is not None and left < 1:
            origin = "the budget is spent"
        if isinstance(origin, float):
            later = origins.later_case(last.diagnosis.case, origin)
            s2 = dataclasses.replace(s, budget=left)
            if budget_problem(later, s2, True, "budget") is not None:
                origin = f"the budget left ({left} calls) cannot cover a later window"
        if isinstance(origin, str):
            break
        prefix = "later-" if len(docs) == 1 else f"later{len(docs) + 1}-"  # window 3: later3-
        log(f"later origin: the history fitted to day {origin:g}")
        try:
            last = diagnose_window(later, counted, s2, last.document["calibrated"], None,
                                   lambda msg, p=prefix: log(f"{p[:-1]} window: {msg}"),
                                   on_step, prefix)
        except RuntimeError as exc:  # the earlier windows' answer stands
            origin = f"the later window (fitted to day {origin:g}) failed: {exc}"
            break
        docs.append(last.document)
        if last.document.get("accepted"):
            break
    if len(docs) > 1:
        doc, named = origins.combine(docs)
        out = last if named else out
        out = Outcome(doc, out.diagnosis, out.final)
        if not named:  # why the rolling origin stopped there
            out.document["no_further_window"] = origin
    else:
        out.document["windows"], out.document["named_on"] = [], None
        out.document["no_later_window"] = origin
    out.document["cost"] = {**out.document.get("cost", {}), "simulations": count["runs"],
                            "sim_time_s": count["sim_time_s"],
                            "wall_time_s": time.perf_counter() - started}
    return out


def diagnose(case: Case, evaluate_batch: EvaluateBatch, *, calibrated: dict | None = None,
             initial: dict | None = None, settings: DiagnosisSettings | None = None,
             out_dir: Path | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Run every step of every round and window; return the diagnosis document (also
    written to ``out_dir``)."""
    out = diagnose_all(case, evaluate_batch, calibrated=calibrated, initial=initial,
                       settings=settings, log=log)
    out.report(out_dir)
    return out.document
