"""The campaign report's identifiability section (Markdown, HTML through it, ``report.json``
and ``hmflow tables``): what the data pin down at the best call, from the journaled calls
alone.

The Jacobian is a forward-difference stencil among the campaign's journaled calls
(:func:`hmcore.scoring.identifiability.find_stencil`): at the best call, or at the nearest call
within :data:`~hmcore.scoring.identifiability.MAX_BASE_DISTANCE` of it that has one (``lm``
computes a whole one where a descent starts, after a trial rejected on secant columns, and
where a descent ends on the campaign's best call). Its residuals are the noise-whitened residuals of the fitted
history, recomputed from each record's simulated values under the noise the campaign ended
with (the latest ``noise`` artifact, else the case's): the residuals the campaign's likelihood
is of, without the physics penalty's entry. A record without simulated values (an older
journal's) gives its own stored ``residuals``. A campaign with no stencil near its best call
gets a section that says so and how to get one: a report is rebuilt without a simulator, so it
never runs the missing calls.

The mathematics (the Laplace approximation, its convention on the residual variance) is
:mod:`hmcore.scoring.identifiability`'s.
"""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass

import numpy as np
import pandas as pd

from hmcore.calibration.loop import best_record
from hmcore.fields.latent import prior_residuals
from hmcore.model.parameters import Parameter, Scaling
from hmcore.reporting.paper_tables import markdown_table
from hmcore.scoring.identifiability import (
    MAX_BASE_DISTANCE,
    MAX_STENCIL_STEP,
    PAIR_CORRELATION,
    UNINFORMED_SHARE,
    Identifiability,
    Stencil,
    find_stencil,
    identifiability,
    laplace,
    stencil_jacobian,
)
from hmcore.scoring.observations import ObservationSet
from storage import ArtifactStore, EvaluationJournal
from storage.jsonable import to_jsonable

JACOBIAN_OFFSET = 1_000_000
"""Where the runs of a Jacobian made after the fit (:func:`jacobian_journal`) sit among the
calls' indices: run k of that journal is index ``JACOBIAN_OFFSET + k``."""
WHITENED = "whitened"
"""Residual source: recomputed from the records' simulated values under the final noise."""
STORED = "stored"
"""Residual source: the records' own ``residuals`` (a journal from before records kept
simulated values)."""


@dataclass(frozen=True, eq=False)
class Finding:
    """The identifiability of a campaign's best call: ``result`` (None when it could not be
    computed, ``reason`` saying why and how to get it), the best call's index, the stencil the
    Jacobian came from and where its residuals came from (:data:`WHITENED` or
    :data:`STORED`)."""

    result: Identifiability | None
    reason: str = ""
    best_index: int | None = None
    stencil: Stencil | None = None
    source: str = ""
    agent: str = ""


def observation_set(rows: pd.DataFrame, noise: dict | None, summary: pd.DataFrame | None,
                    history_end: float | None, tolerance_days: float) -> ObservationSet:
    """The observation set whose whitening the campaign's final objective applied, from stored
    tables: the weighed ``rows`` (``observations.parquet``), the noise's per-quantity ``rho``
    (``noise`` = :meth:`~hmcore.calibration.objective.Objective.describe`, else ``summary``'s)
    and the wells' own stated rho where the noise summary (``noise.parquet``) lists them apart."""
    rho = {str(k): float(v) for k, v in ((noise or {}).get("rho") or {}).items()}
    rho_well: dict[str, dict[str, float]] = {}
    if summary is not None and not summary.empty and "rho" in summary:
        for q, part in summary.groupby("quantity", sort=False):
            if str(q) not in rho:
                every = part[part.wells == "all"]
                rho[str(q)] = float((every if len(every) else part).rho.iloc[0])
        for r in summary.itertuples():
            if r.wells != "all" and math.isfinite(r.rho) and abs(r.rho - rho[r.quantity]) > 1e-12:
                for w in str(r.wells).split(","):
                    rho_well.setdefault(r.quantity, {})[w.strip()] = float(r.rho)
    return ObservationSet(rows.reset_index(drop=True), rho, float(tolerance_days), history_end,
                          rho_well=rho_well)


def residuals_of(record: dict, obs: ObservationSet | None) -> tuple[np.ndarray | None, str]:
    """A record's whitened residuals of the fitted history (None for a failed run or one that
    kept none) and their source."""
    if record.get("status") == "FAIL":
        return None, ""
    sim = record.get("simulated")
    if sim is not None and obs is not None and len(sim) == len(obs.rows):
        sim = np.array([np.nan if v is None else v for v in sim], float)
        z = (sim - obs.rows.observed.to_numpy(float)) / obs.rows.sigma.to_numpy(float)
        return obs.whiten(z, "fit"), WHITENED
    if record.get("residuals") is not None:
        return np.nan_to_num(np.asarray(record["residuals"], float)), STORED
    return None, ""


def assess(records: list[dict], parameters: list[dict], best_index: int,
           obs: ObservationSet | None, n_noise: int | None = None, agent: str = "",
           prior: tuple[str, ...] = ()) -> Finding:
    """The identifiability at call ``best_index`` of a campaign's ``records`` (its journal in
    call order, each with ``action``, ``status`` and ``simulated`` or ``residuals``), for the
    case's ``parameters`` (``case.json``'s), whitened by ``obs``; ``n_noise``: the residuals
    that are noise (default: the vector's length); ``prior``: latent coefficients whose
    standard normal prior joins the residuals, as in the campaign's objective
    (:mod:`hmcore.calibration.objective`), so that the posterior is the prior's too."""
    space = [Parameter.model_validate(p) for p in parameters]
    names = [p.name for p in space]
    if any(r.get("action") is None for r in records):
        return Finding(None, "The journal's records keep no scaled point: there is no "
                       "stencil to find.", best_index, agent=agent)
    by_index = {int(r["index"]): r for r in records}
    order = sorted(by_index)
    pos = {i: k for k, i in enumerate(order)}
    actions = np.array([np.asarray(by_index[i]["action"], float) for i in order])
    if actions.ndim != 2 or actions.shape[1] != len(names):
        return Finding(None, "The journal's points do not have one coordinate per parameter.",
                       best_index, agent=agent)
    usable = np.array([by_index[i].get("status") != "FAIL" and (
        by_index[i].get("simulated") is not None or by_index[i].get("residuals") is not None)
        for i in order])
    stencil = find_stencil(actions, usable, pos[best_index])
    if stencil is None:
        return Finding(None, _no_stencil(len(names), best_index, agent), best_index, agent=agent)
    stencil = Stencil(order[stencil.base], tuple(order[j] for j in stencil.runs),
                      stencil.steps, stencil.distance)
    base, source = _with_prior(by_index[stencil.base], obs, prior)
    runs = [_with_prior(by_index[j], obs, prior)[0] for j in stencil.runs]
    if base is None or any(r is None or r.shape != base.shape for r in runs):
        return Finding(None, "The stencil's runs have residual vectors of different lengths.",
                       best_index, stencil, agent=agent)
    J = stencil_jacobian(base, runs, stencil.steps)
    post = laplace(J, base, n_noise if n_noise else len(base))
    result = identifiability(names, Scaling.of(space), actions[pos[best_index]], post)
    return Finding(result, "", best_index, stencil, source, agent)


def _with_prior(record: dict, obs: ObservationSet | None, prior: tuple[str, ...]
                ) -> tuple[np.ndarray | None, str]:
    r, source = residuals_of(record, obs)
    if r is None or not prior:
        return r, source
    return np.concatenate([r, prior_residuals(record.get("params") or {}, prior)]), source


def _no_stencil(d: int, best_index: int, agent: str) -> str:
    method = f"this campaign's method ({agent})" if agent else "this campaign's method"
    return (f"Identifiability needs the Jacobian of the whitened residuals at the "
            f"best call, and the journal holds no finite-difference stencil there (a call one "
            f"step of at most {MAX_STENCIL_STEP:g} scaled units along each of the {d} "
            f"parameters in turn, from call {best_index + 1} or from a call within "
            f"{MAX_BASE_DISTANCE:g} of it): {method} computed none there. A report is rebuilt "
            "without the simulator, so it does not run those calls.")


def hint(case_source: str) -> str:
    """The command that makes a campaign with a Jacobian at its best call."""
    return shlex.join(["hmflow", "run", "--case", case_source, "--agent", "lm"])


def jacobian_journal(best_index: int) -> str:
    """The journal of the finite-difference runs made after the fit at call ``best_index``
    (0-based) when the campaign's own calls hold no stencil there (:mod:`tasks.posterior`),
    outside the budget."""
    return f"jacobian-{best_index + 1:06d}"


def call_label(index: int) -> str:
    """A stencil run's name for a reader: ``call N`` of the campaign, or ``J-run k`` of the
    Jacobian made after the fit."""
    if index >= JACOBIAN_OFFSET:
        return f"J-run {index - JACOBIAN_OFFSET + 1}"
    return f"call {index + 1}"


def load_identifiability(store: ArtifactStore, campaign: str) -> Finding | None:
    """The identifiability of a stored campaign's best call, from its stored records, the
    runs of a Jacobian made there after the fit (:func:`jacobian_journal`, at indices from
    :data:`JACOBIAN_OFFSET`), its case and final noise (None when it has no results)."""
    results = store.latest(campaign, "results")
    case = store.latest(campaign, "case")
    if results is None or case is None:
        return None
    doc = results.read_json("records.json")
    case_doc = case.read_json("case.json")
    agent = (store.settings(campaign) or {}).get("agent", "")
    records = doc["records"]
    best = best_record(records, doc.get("objective", "E"))
    if best is None:
        return Finding(None, "The campaign has no valid call to stand at.",
                       agent=agent)
    noise = store.latest(campaign, "noise")
    source = noise if noise is not None else case
    obs = None
    if "observations.parquet" in source.files:
        summary = source.read_parquet("noise.parquet") if "noise.parquet" in source.files \
            else None
        obs = observation_set(source.read_parquet("observations.parquet"), doc.get("noise"),
                              summary, case_doc.get("fit_history_end_days"),
                              case_doc.get("time_tolerance_days", 30.0))
    n_noise = (doc.get("noise") or {}).get("n_noise") or (obs.n_noise("fit") if obs else None)
    after = EvaluationJournal(store, campaign, jacobian_journal(int(best["index"]))).rows()
    records = records + [{**r, "index": JACOBIAN_OFFSET + int(r["index"])} for r in after]
    latent = case_doc.get("latent") or {}
    prior = tuple(p["name"] for p in case_doc["parameters"] if p.get("kind") == "latent") \
        if latent.get("prior") == "regularised" and doc.get("objective") == "likelihood" else ()
    return assess(records, case_doc["parameters"], int(best["index"]), obs, n_noise, agent,
                  prior)


# ------------------------------------------------------------------ words and tables
def _num(v: float) -> str:
    if v is None or not math.isfinite(v):
        return "inf" if v is not None and v > 0 else "n/a"
    return f"{v:.4g}"


def truth_inside(found: Identifiability, truth: dict[str, float] | None) -> dict[str, bool]:
    """Per parameter with a known true value: whether it lies in the 95 % interval."""
    return {name: bool(found.low[k] - 1e-12 <= truth[name] <= found.high[k] + 1e-12)
            for k, name in enumerate(found.names) if truth and name in truth}


def parameter_frame(found: Identifiability, truth: dict[str, float] | None = None
                    ) -> pd.DataFrame:
    """One row per parameter, as printed: best value, sd, 95 % interval, the share of its range
    the interval covers, and what is to be said of it; with a known ``truth``, the true value
    and whether the interval holds it."""
    inside = truth_inside(found, truth)
    rows = []
    for k, name in enumerate(found.names):
        sd = _num(found.sd[k])
        if found.log[k] and math.isfinite(found.factor[k]):
            sd += f" (×/÷ {found.factor[k]:.3g})"
        notes = []
        if found.laplace.undetermined[k]:
            notes.append("undetermined")
        if k in found.uninformed:
            notes.append("not informed")
        if found.clipped_low[k]:
            notes.append("clipped at low")
        if found.clipped_high[k]:
            notes.append("clipped at high")
        rows.append({"parameter": name, "best": _num(found.best[k]), "sd": sd,
                     "95 % interval": f"[{_num(found.low[k])}, {_num(found.high[k])}]",
                     "of range": f"{100 * found.share[k]:.0f} %",
                     "note": ", ".join(notes)})
        if inside:
            rows[-1].update({"truth": _num(truth[name]) if name in inside else "",
                             "truth inside": {True: "yes", False: "NO"}.get(inside.get(name),
                                                                          "")})
    return pd.DataFrame(rows)


def correlation_frame(found: Identifiability) -> pd.DataFrame:
    """The correlation matrix, two decimals."""
    c = found.laplace.correlation
    return pd.DataFrame([{"parameter": a, **{b: f"{c[i, j]:+.2f}" if i != j else "1"
                                             for j, b in enumerate(found.names)}}
                         for i, a in enumerate(found.names)])


def pair_sentences(found: Identifiability) -> list[str]:
    """The pairs the data cannot separate, in words."""
    out = []
    for i, j, c in found.pairs:
        a, b = found.names[i], found.names[j]
        move = ("raising one and lowering the other" if c < 0 else "raising both together")
        out.append(f"{a} and {b} trade off (correlation {c:+.2f}): the data fix their "
                   f"combination, not each ({move} leaves the fit about as it is).")
    return out


def uninformed_sentences(found: Identifiability) -> list[str]:
    """The parameters the data do not inform, in words."""
    out = []
    for k in found.uninformed:
        if found.laplace.undetermined[k]:
            why = "no combination of the data moves it alone: its interval is its whole range"
        else:
            why = f"its 95 % interval covers {100 * found.share[k]:.0f} % of its range"
        out.append(f"{found.names[k]}: the data do not inform it ({why}).")
    return out


def summary_sentences(finding: Finding) -> list[str]:
    """Where the Jacobian stands, what its residuals are, and the convention on their
    variance."""
    found, st = finding.result, finding.stencil
    post = found.laplace
    d = len(found.names)
    runs = ", ".join(call_label(j) for j in st.runs)
    if st.base == finding.best_index:
        at = f"at the best call (call {st.base + 1}; from {runs}"
    else:
        at = (f"at call {st.base + 1}: the best call (call {finding.best_index + 1}) has no "
              f"full stencil, call {st.base + 1} is the nearest call that has one, "
              f"{st.distance:.3g} scaled units away (from {runs}")
    source = ("the noise-whitened residuals of the fitted history under the noise the campaign "
              "ended with" if finding.source == WHITENED else
              "the residuals stored in the records (a journal from before records kept "
              "simulated values)")
    factor = math.sqrt(post.s2) if math.isfinite(post.s2) else float("nan")
    where = (f"The Jacobian, of {source}, is a forward difference {at}, one step along each "
             f"parameter). The Laplace approximation of the posterior there: "
             f"covariance `(J^T J)^-1` in the scaled parameters (each range mapped to [-1, 1], "
             f"in log(value) for a log-scaled parameter), {post.rank} of {d} directions "
             "determined by the data. Standard deviations and intervals are in the case's "
             "units (a log-scaled parameter's also as a factor, ×/÷; its interval is not "
             "symmetric about the best value); the 95 % interval is the best value ± 1.96 sd, "
             "clipped to the parameter's range where marked.")
    reading = (" (the residuals are larger than the noise says: read the intervals as too "
               "narrow)" if factor > 1.5 else " (the residuals are smaller than the noise "
               "says: it may be overstated, the intervals too wide)" if factor < 2 / 3 else "")
    variance = (f"Not scaled by the residual variance: the residuals are in units of the noise "
                f"the campaign's objective assumes (given, stated, or estimated from the data "
                f"and refined from the fit), so that noise is the data's covariance. Here "
                f"chi2 = {post.chi2:.5g} over n = {post.n} noise rows, chi2/(n - d) = "
                f"{_num(post.s2)}: the regression convention for an unknown noise level "
                f"(scaling by it) would make every sd {factor:.3g} times as wide{reading}.")
    local = ("The approximation is local: it holds where the responses are about linear in "
             "the parameters across the interval; an interval many finite-difference steps "
             "wide extrapolates the slopes at the best call.")
    lines = [where, "", variance, "", local]
    return lines


def identifiability_markdown(finding: Finding | None, case_source: str = "CASE",
                             truth: dict[str, float] | None = None, level: int = 2
                             ) -> list[str]:
    """The section as Markdown lines (empty: no results); ``case_source``: the case file the
    hint's command names; ``truth``: the known true parameters, if any."""
    h = "#" * level
    lines = [f"{h} Identifiability: what the data pin down", ""]
    if finding is None:
        return []
    found = finding.result
    if found is None:
        how = (f"To get one: a least-squares campaign, `{hint(case_source)}` (its journal "
               "holds the finite-difference runs around its best calls).")
        return [*lines, f"Not computed. {finding.reason}", "", how, ""]
    lines += summary_sentences(finding) + [""]
    lines += [markdown_table(parameter_frame(found, truth)), ""]
    inside = truth_inside(found, truth)
    if inside:
        held = sum(inside.values())
        lines += [f"The known truth lies inside {held} of {len(inside)} 95 % intervals.", ""]
    lines += [f"{h}# Correlations", "",
              "Of the scaled coordinates (of log(value) for a log-scaled parameter).", "",
              markdown_table(correlation_frame(found)), ""]
    lines += [f"{h}# Pairs the data cannot separate", ""]
    pairs = pair_sentences(found)
    lines += ([f"- {s}" for s in pairs] if pairs else [
        f"None: no two parameters' correlation is beyond ±{PAIR_CORRELATION:g}."]) + [""]
    lines += [f"{h}# Parameters the data do not inform", ""]
    free = uninformed_sentences(found)
    every = (f"None: every parameter's 95 % interval covers at most "
             f"{100 * UNINFORMED_SHARE:.0f} % of its range.")
    lines += ([f"- {s}" for s in free] if free else [every]) + [""]
    return lines


def identifiability_document(finding: Finding | None,
                             truth: dict[str, float] | None = None) -> dict | None:
    """The section as ``report.json``'s ``identifiability`` (None: no results)."""
    if finding is None:
        return None
    found, st = finding.result, finding.stencil
    doc: dict = {"computed": found is not None, "reason": finding.reason,
                 "best_call": None if finding.best_index is None else finding.best_index + 1,
                 "method": finding.agent}
    if found is None:
        return to_jsonable(doc)
    post = found.laplace
    inside = truth_inside(found, truth)
    doc.update({
        "jacobian_base_call": st.base + 1,
        "jacobian_runs": [j + 1 if j < JACOBIAN_OFFSET else None for j in st.runs],
        "jacobian_run_labels": [call_label(j) for j in st.runs],
        "steps_scaled": list(st.steps), "base_distance_scaled": st.distance,
        "residuals": finding.source, "n": post.n, "chi2": post.chi2,
        "chi2_per_dof": post.s2, "scaled_by_residual_variance": False, "rank": post.rank,
        "interval": "best ± 1.96 sd in scaled units, clipped to the range",
        "parameters": [{
            "name": name, "best": found.best[k], "sd": found.sd[k],
            "sd_scaled": post.sd[k], "factor": found.factor[k] if found.log[k] else None,
            "low": found.low[k], "high": found.high[k],
            "clipped_low": bool(found.clipped_low[k]),
            "clipped_high": bool(found.clipped_high[k]),
            "share_of_range": found.share[k], "informed": k not in found.uninformed,
            "undetermined": bool(post.undetermined[k]), "truth_inside": inside.get(name)}
            for k, name in enumerate(found.names)],
        "correlation": {"names": list(found.names), "matrix": post.correlation},
        "pairs": [{"a": found.names[i], "b": found.names[j], "correlation": c}
                  for i, j, c in found.pairs],
        "uninformed": [found.names[k] for k in found.uninformed],
        "pair_correlation": PAIR_CORRELATION, "uninformed_share": UNINFORMED_SHARE})
    return to_jsonable(doc)
