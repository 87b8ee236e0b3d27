"""The answer of a diagnosis round: its explanations ranked by their support in the data
(:mod:`hmcore.diagnosis.evidence`) and, when the data cannot separate them, the measurement
that would (:mod:`hmcore.diagnosis.separation`).

:func:`explanations` gathers the round's fits - ``none`` (the calibrated model), every
recalibrated candidate, ``unexplained`` when the residual analysis localises a miss beyond
noise - from the round's frozen results; :func:`section` ranks them and writes the
document's ``answer``; :func:`with_pair` ranks a stored answer again with round 2's pair;
:func:`attach` puts the answer into the round's document and a sentence into its verdict (the
existing verdict is kept: where one cause dominates it is the same cause). Nothing here
simulates: the separating measurement is read from runs already made.
"""

from __future__ import annotations

import math

import numpy as np

from hmcore.diagnosis import evidence, separation
from hmcore.diagnosis.decision import localise
from hmcore.diagnosis.evidence import AnswerKind, Fit
from hmcore.diagnosis.runs import Run
from hmcore.diagnosis.state import Context, Round
from hmcore.scoring.noise import RESPONSE_OF
from hmcore.scoring.observations import ObservationSet

MAX_SEPARATIONS = 3
"""Pairs of the answer's set whose separating measurement is reported (the first with each
other member, best first)."""


def _eig(jacobian: np.ndarray | None) -> np.ndarray:
    e = evidence.jtj_eigenvalues(jacobian)
    return np.zeros(0) if e is None else e


def explanations(ctx: Context, state: Round, gain: dict | None = None
                 ) -> tuple[list[Fit], dict[str, Run]]:
    """The round's explanations and the run of each (``unexplained`` has none of its own: its
    predictions are the calibrated model's). A candidate whose recalibration kept no Jacobian
    takes the score test's (the globals' and its sensitivity at the calibrated point).
    ``gain``: the decision's (the calibrated model's E, fitted and held back)."""
    cal, rank, recal = state.calibrated, state.ranking, state.recalibration
    base, gain = cal.run, gain or {}
    g_eig = _eig(cal.jacobian if cal.jacobian is not None else rank.jacobian)
    fits = [Fit("none", "none", base.ssr_fit, base.ssr_heldout, g_eig,
                fit_E=gain.get("fit_before"), heldout_E=gain.get("heldout_before"))]
    runs = {"none": base}
    by_id = {c.id: c for c in rank.candidates}
    for cid, rec in recal.confirmed.items():
        eig = rec.get("jtj_eigenvalues")
        if eig is None:
            eig = _eig(np.column_stack([rank.jacobian, rank.sensitivity[cid]])
                       if cid in rank.sensitivity else None)
        fits.append(Fit(cid, by_id[cid].kind, float(rec["ssr_fit_after"]),
                        float(rec["ssr_heldout_after"]), np.asarray(eig, float),
                        fit_E=rec.get("fit_after"), heldout_E=rec.get("heldout_after")))
        if cid in recal.runs:
            runs[cid] = recal.runs[cid]
    found, _, m = localise(state.residuals, ctx.settings.unexplained_alpha)
    if found:
        ssr, k = unexplained_fit(cal.obs, base.r_fit, found)
        fits.append(Fit("unexplained", "unexplained", ssr, base.ssr_heldout, g_eig, n_bic=k,
                        log_prior=-k * math.log(max(m, 1)),
                        fit_E=fits[0].fit_E, heldout_E=fits[0].heldout_E))
    return fits, runs


def unexplained_fit(obs: ObservationSet, r_fit: np.ndarray, found: list[dict]
                    ) -> tuple[float, int]:
    """The ``unexplained`` explanation's fit: the calibrated model's whitened fitted residuals
    ``r_fit`` (shape (n_fit,)) less their least-squares projection on one free term per
    finding of :func:`hmcore.diagnosis.decision.localise` - a bias (or a drift in time,
    whichever its z is larger for) over the finding's well, response and days, whitened as the
    residuals are. Returns (the SSR left, the rank of those terms: the parameters it fits).
    Findings overlap (a whole window and its halves): the rank counts each direction once."""
    rows = obs.rows
    resp = rows["quantity"].map(RESPONSE_OF).to_numpy()
    well, days = rows["well"].to_numpy(), rows["days"].to_numpy(float)
    fit = rows["period"].to_numpy() == "fit"
    cols = []
    for f in found:
        d0, d1 = f["days"]
        inside = fit & (well == f["well"]) & (resp == f["response"])
        if d0 is not None and d1 is not None:
            inside &= (days >= d0) & (days <= d1)
        if not inside.any():
            continue
        if abs(f["z_trend"]) > abs(f["z_bias"]):
            t = days[inside] / 365.25
            col = np.zeros(len(rows))
            col[inside] = t - t.mean()
        else:
            col = inside.astype(float)
        cols.append(obs.whiten(col, "fit"))
    r = np.asarray(r_fit, float)
    if not cols:
        return float(r @ r), 0
    X = np.column_stack(cols)
    coef, _, rank, _ = np.linalg.lstsq(X, r, rcond=None)
    left = r - X @ coef
    return float(left @ left), int(rank)


def sigma_by_series(obs: ObservationSet) -> dict[tuple[str, str], float]:
    """Per (well, quantity), the median noise sigma of its measured rows."""
    rows = obs.rows
    ok = np.isfinite(rows["sigma"].to_numpy(float)) & (rows["sigma"].to_numpy(float) > 0)
    med = rows[ok].groupby(["well", "quantity"])["sigma"].median()
    return {(str(w), str(q)): float(v) for (w, q), v in med.items()}


def _fit_doc(f: Fit) -> dict:
    return {"id": f.id, "kind": f.kind, "ssr_fit": f.ssr_fit, "ssr_heldout": f.ssr_heldout,
            "jtj_eigenvalues": [float(x) for x in f.jtj_eigenvalues], "n_bic": f.n_bic,
            "log_prior": f.log_prior, "fit_E": f.fit_E, "heldout_E": f.heldout_E}


def _fit_of(d: dict) -> Fit:
    return Fit(d["id"], d["kind"], float(d["ssr_fit"]), float(d["ssr_heldout"]),
               np.asarray(d["jtj_eigenvalues"], float), int(d["n_bic"]),
               float(d["log_prior"]), d.get("fit_E"), d.get("heldout_E"))


def section(fits: list[Fit], n_fit: int, runs: dict[str, Run], obs: ObservationSet,
            mass: float = evidence.MASS) -> dict:
    """The document's ``answer``: the ranked explanations with their weights, the answer
    (``kind`` single or set, ``members``), and for a set where its members' predictions
    differ most (``separations``) and the sentence (``text``)."""
    ranked = evidence.rank(fits, n_fit, mass)
    seps: list[separation.Separation] = []
    if ranked.kind is AnswerKind.SET:
        ids = [k for k in ranked.members if k in runs and k != "unexplained"]
        frames = {k: runs[k].responses for k in ids if runs[k].responses is not None}
        if len(frames) > 1:
            table = separation.tabulate(frames, sigma_by_series(obs))
            pairs = separation.separations(*table)
            first = next(iter(frames))
            seps = sorted((p for p in pairs if first in (p.a, p.b)),
                          key=lambda p: -p.z)[:MAX_SEPARATIONS]
    return _document(ranked, fits, seps, obs.history_end_days, n_fit)


def _document(ranked: evidence.Ranked, fits: list[Fit], seps, history_end, n_fit) -> dict:
    items = [{"id": x.fit.id, "kind": x.fit.kind, "weight": x.weight,
              "log_evidence": x.log_evidence, "log_likelihood": x.log_likelihood,
              "log_occam": x.log_occam, "method": x.fit.method.value,
              "n_parameters": x.fit.n_parameters, "ssr_fit": x.fit.ssr_fit,
              "ssr_heldout": x.fit.ssr_heldout, "fit_E": x.fit.fit_E,
              "heldout_E": x.fit.heldout_E} for x in ranked.items]
    sep_docs = [{"a": p.a, "b": p.b, "well": p.well, "quantity": p.quantity, "day": p.day,
                 "z": p.z, "from_day": p.from_day, "sentence": p.sentence(history_end)}
                for p in seps]
    out = {"kind": ranked.kind.value, "members": list(ranked.members), "mass": ranked.mass,
           "bayes_factor": (None if math.isinf(ranked.bayes_factor)
                            else ranked.bayes_factor),
           "scale": ranked.scale, "n_fit": int(n_fit), "explanations": items,
           "separations": sep_docs, "fits": [_fit_doc(f) for f in fits]}
    out["text"] = text(out)
    return out


def text(answer: dict) -> str:
    """The answer in words."""
    items = {x["id"]: x for x in answer["explanations"]}
    first = answer["explanations"][0]
    if answer["kind"] == AnswerKind.SINGLE.value:
        t = f"the data support {first['id']} ({100 * first['weight']:.0f} % of the weight"
        if len(answer["explanations"]) > 1:
            t += (f"; Bayes factor {answer['bayes_factor']:.3g} over "
                  f"{answer['explanations'][1]['id']}")
        return t + ")"
    members = [items[k] for k in answer["members"]]
    parts = ", ".join(f"{m['id']} ({100 * m['weight']:.0f} %: fitted SSR "
                      f"{m['ssr_fit']:.0f}, held-back {m['ssr_heldout']:.0f})" for m in members)
    t = (f"the data cannot separate {parts}: together "
         f"{100 * sum(m['weight'] for m in members):.0f} % of the weight")
    if answer["separations"]:
        t += "; " + "; ".join(s["sentence"] for s in answer["separations"])
    return t


def with_pair(answer: dict, pair: Fit, mass: float | None = None) -> dict:
    """A stored ``answer`` ranked again with a two-cause explanation (round 2's pair, its
    SSRs under round 1's noise model); the separations are kept when the set is."""
    fits = [_fit_of(d) for d in answer["fits"] if d["id"] != pair.id] + [pair]
    ranked = evidence.rank(fits, answer["n_fit"], mass or answer["mass"])
    keep = [s for s in answer["separations"]
            if s["a"] in ranked.members and s["b"] in ranked.members]
    seps = [separation.Separation(s["a"], s["b"], s["well"], s["quantity"], s["day"], s["z"],
                                  s["from_day"]) for s in keep]
    doc = _document(ranked, fits, seps, None, answer["n_fit"])
    doc["separations"] = keep
    doc["text"] = text(doc)
    return doc


def verdict_note(doc: dict) -> str:
    """What the answer adds to the verdict: nothing when its one cause is the document's
    first; otherwise the set, or the cause the evidence prefers."""
    a = doc.get("answer")
    if not a:
        return ""
    first = (doc.get("causes") or [{}])[0].get("id")
    if a["kind"] == AnswerKind.SINGLE.value and a["members"][0] == first:
        return f" ({a['text']})"
    return f". By the evidence: {a['text']}"


def attach(doc: dict, ctx: Context, state: Round) -> dict:
    """``doc`` (the round's document) with its ``answer`` and the verdict's note."""
    fits, runs = explanations(ctx, state, doc.get("gain"))
    obs = state.calibrated.obs
    out = dict(doc)
    out["answer"] = section(fits, obs.n_noise("fit"), runs, obs, ctx.settings.evidence_mass)
    out["verdict"] = doc["verdict"] + verdict_note(out)
    return out
