"""Forward selection of a second cause: put the first cause in the model, diagnose again, and
accept what the second round finds with its own gain.

Two effects of different kinds hide each other from a one-cause diagnosis: the strongest
candidate fits the fitted history far beyond noise, but without the second effect it predicts
the held-back history worse, and the held-back rule vetoes it (then the weaker other cause is
accepted alone). Greedy forward selection answers it:

1. round 1 is the ordinary diagnosis (:mod:`hmcore.diagnosis.workflow`);
2. its first cause - the selected one, or else the best recalibrated fit beyond noise that the
   held-back history vetoed (*tentative*) - joins the case's parameters, at its recalibrated
   values (that simulation is reused, not run again);
3. round 2 analyses, ranks and recalibrates the candidates of the same families on that model
   (the first cause's parameter is recalibrated with the globals), and decides by the same
   rules, against the one-cause model;
4. the combination: a selected first cause stays accepted, and a second cause round 2 selects
   is accepted with its own gain. A tentative first cause is accepted only together with a
   second one, and only when the pair predicts the held-back history better than the
   calibrated model under the round-1 noise model (the same rule,
   :func:`hmcore.diagnosis.confirmation.heldout_confirms`); otherwise round 1's answer stands.

Plain functions of two :class:`Diagnosis` objects; the caller runs round 2's steps (so the
Prefect flow stores them) and nothing here simulates.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass

import numpy as np

from hmcore.diagnosis import answer, decision
from hmcore.diagnosis.budget import budget_problem
from hmcore.diagnosis.confirmation import heldout_confirms, heldout_noise_line
from hmcore.diagnosis.evidence import Fit
from hmcore.diagnosis.candidate import extended_space
from hmcore.diagnosis.runs import heldout_per_well
from hmcore.diagnosis.workflow import Diagnosis


@dataclass(frozen=True)
class Plan:
    """Round 2: the cause it builds on, whether that cause is tentative (vetoed alone by the
    held-back history), and the diagnosis of the model with it (not yet run)."""

    first: str
    tentative: bool
    diagnosis: Diagnosis


def first_cause(doc: dict) -> tuple[str, bool] | None:
    """The cause round 2 builds on: (id, tentative), None when round 1 found nothing that fits
    the fitted history beyond noise."""
    if doc.get("selected"):
        return doc["selected"]["id"], False
    fits = doc.get("fits_beyond_noise") or []
    return (fits[0], True) if fits else None


def plan(d1: Diagnosis, doc1: dict) -> Plan | str:
    """Round 2 of ``d1`` (decided: ``doc1``), or why there is none (a sentence)."""
    s = d1.settings
    if s.max_causes < 2:
        return "max_causes is 1"
    start = first_cause(doc1)
    if start is None:
        return "round 1 found no cause that fits the fitted history beyond noise"
    cid, tentative = start
    by_id = {c.id: c for c in d1.candidates}
    case2 = d1.case.with_space(extended_space(d1.case.space, [by_id[cid]]))
    left = d1.left()
    if left is not None and left < 1:
        return "the budget is spent"
    s2 = dataclasses.replace(s, budget=left, polish_given=False)
    problem = budget_problem(case2, s2, True, "budget")
    if problem is not None:
        return f"the budget left after round 1 ({left} calls) cannot cover a second round"
    d2 = Diagnosis(case2, d1.evaluate_batch, s2, log=lambda msg: d1.log(f"round 2: {msg}"))
    return Plan(cid, tentative, d2)


def run_round(p: Plan, d1: Diagnosis) -> dict:
    """Every step of round 2 (for callers that do not store them one by one)."""
    start_round(p, d1)
    d2 = p.diagnosis
    d2.analyse()
    d2.rank()
    d2.extend()
    d2.recalibrate()
    return d2.decide()


def start_round(p: Plan, d1: Diagnosis) -> dict:
    """Round 2's calibration: the first cause's recalibrated model, its run reused."""
    run = d1.confirmed_runs[p.first]
    return p.diagnosis.calibrate(calibrated=run.values, result=run.result)


def combine(d1: Diagnosis, doc1: dict, p: Plan, doc2: dict) -> tuple[dict, object | None]:
    """The diagnosis of both rounds: the document, and the run of the final model (None when
    round 1's answer stands as it was)."""
    d2, s = p.diagnosis, d1.settings
    second = doc2["selected"]["id"] if doc2.get("selected") else None
    pair_run = d2.confirmed_runs.get(second) if second else None
    doc = copy.deepcopy(doc1)
    doc["cost"]["simulations"] = d1.n_runs + d2.n_runs
    doc["cost"]["sim_time_s"] = d1.sim_time_s + d2.sim_time_s
    base_sc = d1.run_scores(d1.base)
    pair_ok = False
    if pair_run is not None:
        again = d1.rescore(pair_run)  # under the round-1 noise model: the same yardstick
        pair_sc = d1.run_scores(again)
        pair_ok = not p.tentative or heldout_confirms(
            base_sc["ssr_heldout"], again.ssr_heldout, base_sc["E_heldout"],
            pair_sc["E_heldout"], d1.obs.n_noise("heldout"), s)[0]
    second_conf = d2.confirmed.get(second) if second else None
    members = (doc.get("answer") or {}).get("members")
    if pair_run is not None and (doc.get("answer") or {}).get("fits"):
        doc["answer"] = weigh_pair(doc["answer"], p.first, second, again,
                                   second_conf.get("jtj_eigenvalues"))
    doc, final = _both(doc, doc1, doc2, d1, p, second, pair_ok,
                       pair_sc if pair_run else None, again if pair_run else None, pair_run)
    if (doc.get("answer") or {}).get("members") != members:
        doc["verdict"] += ". With round 2's pair weighed too, " + doc["answer"]["text"]
    return doc, final


def _both(doc: dict, doc1: dict, doc2: dict, d1: Diagnosis, p: Plan, second: str | None,
          pair_ok: bool, pair_sc: dict | None, again, pair_run) -> tuple[dict, object | None]:
    """:func:`combine`'s document once round 2 is known (``again``: the pair's run under
    round 1's noise model, ``pair_sc`` its scores, ``pair_ok`` whether it is accepted)."""
    s, d2 = d1.settings, p.diagnosis
    base_sc = d1.run_scores(d1.base)
    first_conf, second_conf = d1.confirmed[p.first], (d2.confirmed.get(second) if second
                                                      else None)
    summary = {"round": 2, "builds_on": p.first, "tentative": p.tentative,
               "accepted": second if pair_ok else None, "verdict": doc2["verdict"],
               "causes": [{k: c[k] for k in ("id", "kind", "wells", "layers", "chi2",
                                             "evidence")} for c in doc2["causes"][:10]],
               "gain": doc2["gain"],
               "simulations": d2.n_runs, "calibrated": doc2["calibrated"]}
    doc["rounds"] = [summary]
    if not pair_ok:
        doc["accepted"] = ([decision.accepted_cause(_cause(doc1, p.first), first_conf, 1)]
                           if not p.tentative else [])
        unexplained = doc2["causes"][0] if doc2["causes"] and \
            doc2["causes"][0]["kind"] == "unexplained" else None
        if p.tentative:
            doc["verdict"] += (f". A second round with {p.first} in the model ({d2.n_runs} "
                               "simulations) found no second cause that makes the pair "
                               f"predict the held-back history: {p.first} stays rejected")
        elif unexplained is not None:
            doc["causes"].insert(1, {**unexplained, "evidence": f"round 2, with {p.first} "
                                     f"in the model: {unexplained['evidence']}"})
            doc["verdict"] += (f". With {p.first} in the model, something no family explains "
                               f"remains: {unexplained['description']}")
            doc = decision.lead_unexplained(doc, s)
        else:
            doc["verdict"] += (f". A second round with {p.first} in the model ({d2.n_runs} "
                               "simulations) found no further cause beyond noise")
            doc["verdict"] += remaining_text(first_conf["ssr_heldout_after"],
                                             d1.obs.n_noise("heldout"), s, p.first)
        return doc, None
    by_id1 = {c["id"]: c for c in doc1["causes"]}
    a = {**_cause(doc1, p.first), "evidence": (
        "accepted with the second cause: alone it fits the fitted history beyond noise but "
        "the held-back history vetoes it" if p.tentative else by_id1[p.first]["evidence"])}
    b = {**_cause(doc2, second), "evidence": (f"round 2, with {p.first} in the model: "
                                              + _cause(doc2, second)["evidence"])}
    doc["accepted"] = [decision.accepted_cause(a, first_conf, 1),
                       decision.accepted_cause(b, second_conf, 2)]
    doc["causes"] = [a, b] + [c for c in doc1["causes"] if c["id"] not in (p.first, second)
                              and c["kind"] != "unexplained"]  # the pair explains it
    values = dict(second_conf["values"])
    doc["selected"] = {**a, "values": values, "second": {**b, "values": values}}
    doc["gain"] = {**doc1["gain"], "fit_after": pair_sc["E"],
                   "heldout_after": pair_sc["E_heldout"], "ssr_fit_after": again.ssr_fit,
                   "ssr_heldout_after": again.ssr_heldout}
    g = doc["gain"]
    head = (f"accepted {p.first} and {second} together: {p.first} alone fits the fitted "
            "history beyond noise but the held-back history vetoed it; with it in the model, "
            f"{second} is selected, and the pair predicts the held-back history"
            if p.tentative else doc1["verdict"] + f". With {p.first} in the model, a second "
            f"cause: {doc2['verdict']}")
    doc["verdict"] = (f"{head}. Both: fitted E {g['fit_before']:.4g} -> {g['fit_after']:.4g}, "
                      f"held-back E {g['heldout_before']:.4g} -> {g['heldout_after']:.4g}"
                      + remaining_text(again.ssr_heldout, d1.obs.n_noise("heldout"), s,
                                       f"{p.first} and {second}", pair=True))
    base_ho = heldout_per_well(d1.case, d1.base.responses)
    doc["per_well_response"] = {"extension": f"{p.first} + {second}", "rows":
                                decision.per_well_table(
                                    base_sc["per_well_response"], base_ho,
                                    second_conf["per_well_response_after"],
                                    second_conf["per_well_response_heldout_after"])}
    return doc, pair_run


def weigh_pair(ans: dict, first: str, second: str, run, eigenvalues: list | None) -> dict:
    """Round 1's answer weighed again with the pair ``first+second`` among the explanations
    (:func:`hmcore.diagnosis.answer.with_pair`): its SSRs those of its run under round 1's
    noise model (``run``, rescored), its curvature round 2's recalibration's (its globals, the
    first cause's parameter and the second's)."""
    pair = Fit(f"{first}+{second}", "pair", run.ssr_fit, run.ssr_heldout,
               np.asarray(eigenvalues if eigenvalues is not None else [], float),
               n_bic=0 if eigenvalues is not None else 2)
    return answer.with_pair(ans, pair)


def remaining_text(ssr_heldout: float, n_heldout: int, s, causes: str,
                   pair: bool = False) -> str:
    """A sentence for the verdict when the model with the accepted ``causes`` still misses the
    held-back history beyond noise (whitened SSR over the noise line of
    :func:`hmcore.diagnosis.confirmation.heldout_noise_line`, under round 1's noise model):
    the answer explains part of the data, not all of it. Empty otherwise."""
    line = heldout_noise_line(n_heldout, s)
    if not n_heldout or ssr_heldout <= line:
        return ""
    more = ("a third cause, or other shapes for these two (hmflow accepts two at most)" if pair
            else "a cause of a family not searched, or of another shape")
    return (f". With {causes} the model still misses the held-back history beyond noise "
            f"(whitened SSR {ssr_heldout:.0f} over {n_heldout} measured points, noise up to "
            f"{line:.0f}): the answer is incomplete - {more} may act")


def _cause(doc: dict, cid: str) -> dict:
    return next(c for c in doc["causes"] if c["id"] == cid)
