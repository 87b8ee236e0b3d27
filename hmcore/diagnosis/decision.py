"""The decision: which recalibrated extension the data accept, which the held-back history
vetoes, the ranked causes, the verdict in words and the gain.

Plain functions of the recalibration records (dicts with the fitted and held-back SSR and E
before and after, :func:`hmcore.diagnosis.confirmation.record`), the score tests and the
settings; nothing here simulates. The rules a record is judged by (the fit line, the held-back
rule) are :mod:`hmcore.diagnosis.confirmation`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hmcore.diagnosis.attribution import Score
from hmcore.diagnosis.confirmation import fit_line, heldout_noise_line
from hmcore.diagnosis.confirmation import heldout_decisive_drop  # noqa: F401  (re-exported:
# hmcore.scenarios.judge imports it from here)
from hmcore.diagnosis.candidate import Candidate
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.ordering import natural_key


# ----------------------------------------------------------------------------- the statistic
def statistic(confirmed: dict[str, dict], confirmed_ok: list[str] | tuple[str, ...],
              base_ssr_fit: float, n_tests: int, s: DiagnosisSettings,
              dated: set[str] = frozenset(), n_noise: int | None = None) -> dict | None:
    """The decision in one statistic per question, for the top recalibrated cause (the first
    of ``confirmed_ok``, else the best fit): against no extension, the likelihood ratio of the
    fitted history (the whitened SSR it removes, ``2 log LR`` under the noise model) with its
    chi-square p-value (1 degree of freedom; 2 for a dated cause, whose date was chosen) and
    that p-value over the ``n_tests`` candidates (Bonferroni), beside the line of its degrees of
    freedom (:func:`fit_line`);
    against the runner-up (the next best recalibrated fit, the same number of parameters), the
    difference of their fitted SSRs, its evidence ratio ``exp(d / 2)``, beside ``tie_band``.
    With ``n_noise`` (the fitted points that are measurement noise: the SSR a model right to
    the noise leaves, on average), ``share``: the part of the misfit beyond noise
    (``base_ssr_fit - n_noise``) the cause removes - near 1 for the whole cause, small for a
    candidate that only catches a projection of something no family makes. None when nothing
    was recalibrated."""
    from scipy.stats import chi2  # slow to import: only when needed

    if not confirmed:
        return None
    by_fit = sorted(confirmed, key=lambda k: confirmed[k]["ssr_fit_after"])
    top = confirmed_ok[0] if confirmed_ok else by_fit[0]
    lr = float(base_ssr_fit - confirmed[top]["ssr_fit_after"])
    dof = 2 if top in dated else 1
    line = fit_line(s, dof)
    p = float(chi2.sf(max(lr, 0.0), dof))
    excess = None if n_noise is None else float(base_ssr_fit - n_noise)
    share = (None if excess is None or excess <= 0 else float(min(max(lr, 0.0) / excess, 1.0)))
    out = {"cause": top,
           "vs_none": {"lr": lr, "dof": dof, "p": p, "p_family": min(1.0, n_tests * p),
                       "excess": excess, "share": share,
                       "tests": int(n_tests), "false_alarm": s.false_alarm,
                       "line": line, "beyond": bool(lr > line)},
           "vs_runner_up": None}
    runner = next((k for k in by_fit if k != top), None)
    if runner is not None:
        d = float(confirmed[runner]["ssr_fit_after"] - confirmed[top]["ssr_fit_after"])
        out["vs_runner_up"] = {"runner_up": runner, "lr": d,
                               "evidence_ratio": math.exp(min(d / 2.0, 700.0)),
                               "line": s.tie_band, "apart": bool(d > s.tie_band)}
    return out


def statistic_text(st: dict | None) -> str:
    """The statistic in one sentence."""
    if not st:
        return "no candidate was recalibrated"
    v = st["vs_none"]
    text = (f"{st['cause']}: against no extension, the fitted SSR drops by {v['lr']:.1f} "
            f"(chi-square {v['dof']} dof: p {v['p']:.2g}, {v['p_family']:.2g} over "
            f"{v['tests']} candidates; line {v['line']:.1f} at false-alarm rate "
            f"{v['false_alarm']:g})")
    if v.get("share") is not None:
        text += (f", {100 * v['share']:.0f} % of the misfit beyond noise (fitted SSR "
                 f"{v['excess']:.0f} above its noise expectation)")
    r = st["vs_runner_up"]
    if r:
        text += (f"; against the runner-up {r['runner_up']}, by {r['lr']:.1f} more (evidence "
                 f"ratio {r['evidence_ratio']:.3g}; tie band {r['line']:g})")
    return text


# ----------------------------------------------------------------------------- ranked causes
def order_confirmed(confirmed: dict[str, dict], ids: list[str], tie_band: float) -> list[str]:
    """``ids`` by fitted SSR after recalibration; those within ``tie_band`` of the best fit are
    ordered by their held-back SSR (the fitted history cannot tell them apart). Marks each
    record's ``tied``."""
    if not ids:
        return []
    fit = {k: confirmed[k]["ssr_fit_after"] for k in ids}
    best = min(fit.values())
    tied = [k for k in ids if fit[k] <= best + tie_band]
    for k in ids:
        confirmed[k]["tied"] = len(tied) > 1 and k in tied
    tied.sort(key=lambda k: confirmed[k]["ssr_heldout_after"])
    return tied + sorted([k for k in ids if k not in tied], key=lambda k: fit[k])


CAUSE_CONFIRMED_KEYS = ("value", "delta_ssr_fit", "delta_ssr_heldout", "fit_before", "fit_after",
                        "heldout_before", "heldout_after", "fit_beyond_noise",
                        "heldout_beyond_noise", "heldout_within_noise_before", "open_end",
                        "runs")


def cause(c: Candidate, score: Score | None, conf: dict | None, evidence: str) -> dict:
    """A ranked cause: the candidate, its score test and (when recalibrated) its gain."""
    return {"kind": c.kind, "wells": list(c.wells), "layers": list(c.layers),
            "score": score.score if score else None, "chi2": score.chi2 if score else None,
            "description": c.description, "id": c.id, "evidence": evidence,
            "start_day": c.details.get("start_day"), "machine": c.machine(),
            "confirmed": None if conf is None else {k: conf.get(k) for k in CAUSE_CONFIRMED_KEYS}}


def accepted_cause(cause: dict, conf: dict, round_: int) -> dict:
    """An accepted cause with its own gain: E before (the model without it) and after its
    recalibration, and the whitened SSR drops (``conf``: its recalibration record)."""
    return {"id": cause["id"], "kind": cause["kind"], "wells": cause["wells"],
            "layers": cause["layers"], "description": cause["description"], "round": round_,
            "start_day": cause.get("start_day"),
            "value": conf["value"],
            "gain": {k: conf[k] for k in ("fit_before", "fit_after", "heldout_before",
                                          "heldout_after")},
            "delta_ssr_fit": conf["delta_ssr_fit"],
            "delta_ssr_heldout": conf["delta_ssr_heldout"]}


def _evidence(conf: dict) -> str:
    text = "recalibrated: the fitted misfit drops beyond noise"
    if conf.get("open_end"):
        text += f", at the {conf['open_end']} end of its range"
    if conf.get("tied"):
        text += "; as good a fit as another candidate (the held-back history orders them)"
    return text + ("; the held-back history confirms it" if conf["heldout_beyond_noise"]
                   else "; the held-back history does not confirm it")


def localise(residuals: dict | None, alpha: float) -> tuple[list[dict], float, int]:
    """The residual findings still beyond noise after a family-wise correction: every well x
    response x period of :func:`hmcore.diagnosis.residuals.analyse_residuals` makes two tests
    (bias, trend), m in all - the fitted window's periods only: a held-back prediction also
    carries the calibrated parameters' own error, which the noise model does not describe -;
    a finding's |z| must exceed ``norm.isf(alpha / (2 m))`` (two-sided
    Bonferroni: pure noise reaches it with probability at most ``alpha``). Returns (findings
    strongest first - well, response, period, days, z_bias, z_trend -, the z line, m)."""
    from scipy.stats import norm  # slow to import: only when needed

    stats = [(w, r, p, st) for w, resp in ((residuals or {}).get("wells") or {}).items()
             for r, periods in resp.items() for p, st in periods.items()
             if st.get("n") and p != "heldout"]
    m = 2 * len(stats)
    if not m:
        return [], math.inf, 0
    line = float(norm.isf(alpha / (2 * m)))
    found = [{"well": w, "response": r, "period": p,
              "days": [st.get("first_day"), st.get("last_day")],
              "z_bias": float(st.get("z_bias", 0.0)), "z_trend": float(st.get("z_trend", 0.0)),
              "bias": float(st.get("bias", 0.0))}
             for w, r, p, st in stats
             if max(abs(st.get("z_bias", 0.0)), abs(st.get("z_trend", 0.0))) > line]
    found.sort(key=lambda f: -max(abs(f["z_bias"]), abs(f["z_trend"])))
    return found, line, m


def unexplained_cause(found: list[dict], line: float, m: int, alpha: float) -> dict:
    """The ``unexplained`` cause: where the calibrated model misses beyond noise that no
    candidate family explains (wells, responses, periods and days, strongest first)."""
    def where(f: dict) -> str:
        z = f["z_bias"] if abs(f["z_bias"]) >= abs(f["z_trend"]) else f["z_trend"]
        what = "bias" if z == f["z_bias"] else "drift"
        d0, d1 = f["days"]
        days = f", days {d0:.0f}-{d1:.0f}" if d0 is not None and d1 is not None else ""
        return f"{f['well']} {f['response']} ({f['period']}{days}): {what} z = {z:+.1f}"

    wells = sorted({f["well"] for f in found}, key=natural_key)
    return {"kind": "unexplained", "wells": wells, "layers": [], "score": None, "chi2": None,
            "id": "unexplained", "where": found[:20],
            "description": ("the calibrated model misses the data beyond noise where no "
                            "candidate family explains it: " + "; ".join(where(f)
                                                                         for f in found[:5])
                            + (f"; and {len(found) - 5} more" if len(found) > 5 else "")),
            "evidence": (f"residuals beyond noise at family-wise alpha {alpha:g} (|z| > "
                         f"{line:.2f} over {m} bias and trend tests)"),
            "machine": None, "confirmed": None}


def lead_unexplained(doc: dict, s: DiagnosisSettings) -> dict:
    """The answer's lead when an accepted cause explains only part of the data: ``doc`` (a
    finished diagnosis document) with its ``unexplained`` cause moved first when

    - round 2, with the accepted cause in the model, found residuals beyond noise that no
      family explains (an ``unexplained`` cause after the first),
    - the model with the accepted causes still misses the held-back history beyond noise
      (:func:`heldout_noise_line`), and
    - they remove less than ``s.partial_share`` of the misfit beyond noise (the whitened SSR
      less its noise expectation, one per measured point) of the held-back history and of the
      fitted history alike.

    A cause that accounts for a minority of what the data show beyond noise is then not the
    answer but a partial one: it stays accepted (and in the model), listed second, and the
    verdict gives both shares. A cause that holds most of the fitted misfit stays first however
    little of the held-back misfit it removes: a library shape that holds a partial fault only
    in part (the fault over the whole plane) is still its best name. Idempotent; runs nothing
    (a stored document can be given)."""
    causes = doc.get("causes") or []
    at = next((i for i, c in enumerate(causes) if c.get("kind") == "unexplained"), None)
    accepted = doc.get("accepted") or []
    g = doc.get("gain") or {}
    n = g.get("n_heldout_measured") or 0
    if not at or not accepted or not n or g.get("ssr_heldout_after") is None or \
            g.get("ssr_heldout_before") is None:
        return doc
    before, after = float(g["ssr_heldout_before"]), float(g["ssr_heldout_after"])
    line = heldout_noise_line(n, s)
    if after <= line or before <= line:  # within noise after, or nothing to explain before
        return doc
    share = (before - after) / (before - n)
    n_fit = g.get("n_fit_measured") or 0
    fit_before, fit_after = g.get("ssr_fit_before"), g.get("ssr_fit_after")
    if fit_before is None or fit_after is None or fit_before <= n_fit:
        return doc
    fit_share = (float(fit_before) - float(fit_after)) / (float(fit_before) - n_fit)
    if share >= s.partial_share or fit_share >= s.partial_share:
        return doc
    out = dict(doc)
    first = causes[at]
    out["causes"] = [first] + causes[:at] + causes[at + 1:]
    ids = " and ".join(a["id"] for a in accepted)
    out["lead"] = {"rule": "partial", "heldout_share": share, "fit_share": fit_share,
                   "partial_share": s.partial_share}
    out["verdict"] = (f"unexplained: {first['description']} ({first['evidence']}). "
                      f"{ids} explains only {100 * max(share, 0.0):.0f} % of the held-back "
                      f"misfit beyond noise (whitened SSR {before:.0f} -> {after:.0f} over {n} "
                      f"measured points, noise ~{n}, up to {line:.0f}) and "
                      f"{100 * max(fit_share, 0.0):.0f} % of the fitted one: a partial answer "
                      "at most, listed second. " + doc["verdict"])
    if out.get("windows") and out.get("named_on"):
        out["windows"] = [*out["windows"][:-1],
                          {**out["windows"][-1], "first_cause": first["id"]}]
    return out


@dataclass(frozen=True)
class Decision:
    """The ranked causes (``none`` marks the noise level), the selected candidate id (or
    None), the verdict, whether the calibrated model fits the held-back history within noise,
    the gain, the recalibrated candidate whose per-well table is shown, and the recalibrated
    candidates that fit the fitted history beyond noise (held-back confirmed first)."""

    causes: list[dict]
    selected: str | None
    verdict: str
    heldout_quiet: bool
    gain: dict
    shown: str | None
    fits: tuple[str, ...] = ()


def decide(candidates: list[Candidate], scores: dict[str, Score], confirmed: dict[str, dict],
           ranking: dict, base: dict, base_heldout_per_well: dict, n_heldout_measured: int,
           counts: dict, history_end_days: float, s: DiagnosisSettings,
           residuals: dict | None = None) -> Decision:
    """Rank the causes, select an extension (the best recalibrated fit beyond noise that the
    held-back history confirms) and say why.

    ``confirmed``: the recalibration record of each recalibrated candidate; ``ranking``: the
    screening document (``order``, ``beyond_noise``); ``base``: the calibrated model's scores
    (``E``, ``E_heldout``, ``ssr_fit``, ``ssr_heldout``); ``base_heldout_per_well``: its
    held-back E per well and response; ``counts``: ``n_fit``, ``n_heldout``,
    ``n_fit_measured``, ``n_heldout_measured`` of the gain; ``residuals``: the calibrated
    model's residual analysis - when no candidate fits the fitted history beyond noise and a
    finding there is beyond noise (:func:`localise`), the first cause is ``unexplained``,
    localised, not ``none``."""
    by_id = {c.id: c for c in candidates}

    def cause_of(cid: str, evidence: str) -> dict:
        return cause(by_id[cid], scores.get(cid), confirmed.get(cid), evidence)

    confirmed_ok = order_confirmed(confirmed, [k for k, v in confirmed.items()
                                               if v["fit_beyond_noise"]], s.tie_band)
    confirmed_bad = [k for k in confirmed if k not in confirmed_ok]
    unconfirmed = [k for k in ranking["beyond_noise"] if k not in confirmed]
    rest = [k for k in ranking["order"]
            if k not in confirmed_ok and k not in confirmed_bad and k not in unconfirmed]
    # the held-back history has the last word: a candidate it confirms ranks above one
    # that fits the fitted history better but predicts the held-back history worse
    confirmed_ok = ([k for k in confirmed_ok if confirmed[k]["heldout_beyond_noise"]]
                    + [k for k in confirmed_ok if not confirmed[k]["heldout_beyond_noise"]])
    causes = [cause_of(k, _evidence(confirmed[k])) for k in confirmed_ok]
    causes += [cause_of(k, "score test beyond noise (not recalibrated)") for k in unconfirmed]
    top_chi2 = max([scores[k].chi2 for k in scores] or [0.0])
    causes.append({"kind": "none", "wells": [], "layers": [], "score": None,
                   "chi2": s.chi2_threshold, "id": "none",
                   "description": ("nothing beyond noise remains below this line: the "
                                   "noise level of the score test "
                                   f"(chi2 {s.chi2_threshold:g}; the best candidate "
                                   f"reaches {top_chi2:.1f})"),
                   "evidence": "threshold", "machine": None, "confirmed": None})
    causes += [cause_of(k, "recalibrated, but the fitted misfit does not drop beyond noise")
               for k in confirmed_bad]
    causes += [cause_of(k, "score test within noise") for k in rest]

    selected = None
    if confirmed_ok and confirmed[confirmed_ok[0]]["heldout_beyond_noise"]:
        selected = confirmed_ok[0]
    verdict = _verdict(selected, confirmed_ok, confirmed, ranking, by_id,
                       base_heldout_per_well, n_heldout_measured, s)
    # nothing accepted while the calibrated model misses the data beyond noise: no family
    # explains it (none fits the fitted history beyond noise, or those that do, the held-back
    # history vetoes), so the first answer is `unexplained`, localised, not a rejected name
    found, line, m = (localise(residuals, s.unexplained_alpha) if selected is None
                      else ([], 0.0, 0))
    if found:
        causes.insert(0, unexplained_cause(found, line, m, s.unexplained_alpha))
        verdict = (f"unexplained: {causes[0]['description']} ({causes[0]['evidence']}). "
                   + verdict[0].upper() + verdict[1:])
    n_ho = n_heldout_measured  # the rate controls' residuals are 0, not noise
    heldout_quiet = n_ho == 0 or base["ssr_heldout"] <= heldout_noise_line(n_ho, s)
    if selected is None and not heldout_quiet:
        verdict += (f". But the calibrated model does NOT fit the held-back history within "
                    f"noise (whitened SSR {base['ssr_heldout']:.0f} over {n_ho} measured "
                    "points, "
                    f"noise up to {heldout_noise_line(n_ho, s):.0f}): something acts after "
                    f"day {history_end_days:g} that the fitted history does not "
                    "show (a barrier or aquifer reached later, water or gas arriving); fit "
                    "a longer history to find it")
    after = confirmed.get(selected) if selected else None
    gain = {"fit_before": base["E"], "fit_after": after["fit_after"] if after else base["E"],
            "heldout_before": base["E_heldout"],
            "heldout_after": after["heldout_after"] if after else base["E_heldout"],
            "ssr_fit_before": base["ssr_fit"],
            "ssr_fit_after": after["ssr_fit_after"] if after else base["ssr_fit"],
            "ssr_heldout_before": base["ssr_heldout"],
            "ssr_heldout_after": after["ssr_heldout_after"] if after else base["ssr_heldout"],
            **counts}
    shown = selected or (confirmed_ok[0] if confirmed_ok else
                         (next(iter(confirmed)) if confirmed else None))
    return Decision(causes, selected, verdict, bool(heldout_quiet), gain, shown,
                    tuple(confirmed_ok))


def _verdict(selected: str | None, confirmed_ok: list[str], confirmed: dict[str, dict],
             ranking: dict, by_id: dict[str, Candidate], base_heldout_per_well: dict,
             n_heldout_measured: int, s: DiagnosisSettings) -> str:
    """The decision in words."""
    if selected is not None:
        conf = confirmed[selected]
        verdict = (f"accepted {selected}: {by_id[selected].description}; fitted E "
                   f"{conf['fit_before']:.4g} -> {conf['fit_after']:.4g}, held-back E "
                   f"{conf['heldout_before']:.4g} -> {conf['heldout_after']:.4g}")
        if conf.get("open_end"):
            c = by_id[selected]
            verdict += (f" ({selected} stopped at the {conf['open_end']} end of its range, "
                        f"{conf['value']:.4g} in [{c.parameter.low:g}, {c.parameter.high:g}]: "
                        "it may stand in for an effect it does not describe, or for a larger "
                        "one of its kind)")
        if conf["heldout_after"] >= conf["heldout_before"]:
            rises = worst_heldout_rises(base_heldout_per_well,
                                        conf["per_well_response_heldout_after"])
            verdict += (f" (the held-back E does not drop: it weights every point alike, "
                        f"whatever its noise, and noisy responses dominate it there - "
                        f"{rises}; the noise-weighted held-back misfit drops decisively, "
                        f"whitened SSR {conf['ssr_heldout_before']:.0f} -> "
                        f"{conf['ssr_heldout_after']:.0f}"
                        f" over {n_heldout_measured} measured points)")
        elif conf["delta_ssr_heldout"] <= s.heldout_threshold:
            verdict += (f" (the calibrated model already fitted the held-back history "
                        f"within noise, whitened SSR {conf['ssr_heldout_before']:.0f} over "
                        f"{n_heldout_measured} measured points: it cannot confirm "
                        "more than that the "
                        f"extension does not spoil it, SSR change "
                        f"{-conf['delta_ssr_heldout']:+.1f})")
        return verdict
    if confirmed_ok:
        k = confirmed_ok[0]
        conf = confirmed[k]
        return (f"rejected {k}: it improves the fitted history (SSR -"
                f"{conf['delta_ssr_fit']:.0f}) but not the held-back history beyond "
                f"noise (SSR change {-conf['delta_ssr_heldout']:+.1f}, held-back E "
                f"{conf['heldout_before']:.4g} -> {conf['heldout_after']:.4g}); "
                "no extension is selected")
    if confirmed and not ranking["beyond_noise"]:
        return ("no candidate explains more of the residual than noise would: the "
                f"{len(confirmed)} candidate(s) near the line were recalibrated and "
                "none lowers the fitted misfit beyond noise")
    if confirmed:
        return ("the leading candidates were recalibrated but none lowers the fitted "
                "misfit beyond noise; no extension is selected")
    return ("no candidate explains more of the residual than noise would: the "
            "calibrated model is consistent with the data within the noise level")


# ----------------------------------------------------------------------------- per well
def worst_heldout_rises(before: dict, after: dict, n: int = 3) -> str:
    """The ``n`` largest rises of held-back E contributions (well -> response -> E) in words."""
    rises = sorted(((a - before[w][r], w, r, before[w][r], a)
                    for w, per in after.items() for r, a in per.items()
                    if a is not None and before.get(w, {}).get(r) is not None
                    and a > before[w][r]), reverse=True)[:n]
    return ", ".join(f"{w} {r} {b:.3g} -> {a:.3g}" for _, w, r, b, a in rises) or "none"


def per_well_table(before: dict, before_ho: dict, after: dict | None,
                   after_ho: dict | None) -> list[dict]:
    """Rows (well, response) of the fitted and held-back E before and after an extension."""
    rows = []
    for well in sorted(set(before) | set(before_ho), key=natural_key):
        for resp in ("bhp", "oil", "water", "gas"):
            b = before.get(well, {}).get(resp)
            if b is None and before_ho.get(well, {}).get(resp) is None:
                continue
            rows.append({"well": well, "response": resp, "fit_before": b,
                         "fit_after": (after or {}).get(well, {}).get(resp),
                         "heldout_before": before_ho.get(well, {}).get(resp),
                         "heldout_after": (after_ho or {}).get(well, {}).get(resp)})
    return rows
