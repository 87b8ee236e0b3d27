"""Confirmation: does a recalibrated candidate fit the fitted history beyond noise, and does
the held-back history confirm it?

Two rules, in chi-square units of the whitened residuals (the noise model's: pure noise gives
independent standard normal residuals):

- the fit line (:func:`fit_line`): the fitted SSR must drop by more than what one more free
  parameter removes from pure noise over the candidates tested (two for a dated cause);
- the held-back rule (:func:`heldout_confirms`): the extension must predict the history the
  calibration did not see better than the calibrated model, by the held-back misfit E and the
  held-back whitened SSR (:func:`heldout_noise_line`, :func:`heldout_decisive_drop`).

:func:`record` applies both to one recalibrated candidate and writes its record (an entry of
``recalibration.json``). Nothing here simulates. How the lines' values were measured:
docs/diagnosis.md, "Where the settings' values come from".
"""

from __future__ import annotations

import dataclasses
import math

from hmcore.diagnosis.evidence import jtj_eigenvalues
from hmcore.diagnosis.candidate import Candidate, open_end
from hmcore.diagnosis.recalibrate import LevenbergMarquardt
from hmcore.diagnosis.runs import Run, heldout_per_well, run_scores
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.diagnosis.state import Calibrated, Context


# ----------------------------------------------------------------------------- the lines
def fit_line(s: DiagnosisSettings, dof: int = 1) -> float:
    """The line a recalibrated cause's fitted-SSR drop must pass: ``s.fit_threshold`` for one
    parameter; for ``dof`` > 1 (a dated cause: its factor and the date the scan chose) the
    chi-square(``dof``) quantile at the same tail probability, so that every cause faces the
    same false-alarm rate (15.1 over 30 candidates is 18.4 with 2 degrees of freedom)."""
    if dof <= 1:
        return float(s.fit_threshold)
    from scipy.stats import chi2  # slow to import: only when needed

    return float(chi2.isf(chi2.sf(s.fit_threshold, 1), dof))


def heldout_noise_line(n_heldout: int, s: DiagnosisSettings) -> float:
    """Largest held-back whitened SSR still consistent with noise: the chi-square mean
    + ``s.quiet_sd`` standard deviations (``n_heldout``: the measured points, rate controls
    not counted; see :meth:`ObservationSet.n_noise`)."""
    return n_heldout + s.quiet_sd * math.sqrt(2.0 * n_heldout)


def heldout_decisive_drop(n_heldout: int, s: DiagnosisSettings) -> float:
    """A drop of the held-back whitened SSR that noise cannot make, whatever E does: more than
    ``s.quiet_sd`` standard deviations of the chi-square of ``n_heldout`` measured points
    (and more than ``s.heldout_threshold``)."""
    return max(s.heldout_threshold, s.quiet_sd * math.sqrt(2.0 * n_heldout))


def heldout_confirms(ssr_before: float, ssr_after: float, e_before: float, e_after: float,
                     n_heldout: int, s: DiagnosisSettings, decisive: bool = True
                     ) -> tuple[bool, bool]:
    """Does the held-back history confirm an extension? Returns (confirmed, quiet).

    ``ssr_*``: whitened SSR of the held-back points (``n_heldout`` of them) before / after the
    extension; ``e_*``: held-back misfit E. Confirmed: E drops and the SSR drops by more than
    ``s.heldout_threshold``; or, when the calibrated model already fits the held-back points
    within noise (``quiet``: SSR at most :func:`heldout_noise_line`, so they hold no signal to
    explain), E drops and the SSR does not rise by more than ``s.heldout_threshold``; or
    (``decisive``) the SSR drops decisively (by more than :func:`heldout_decisive_drop`) and E
    rises by less than the share ``s.heldout_e_slack``.

    E weights every point alike whatever its noise, so where noisy responses dominate it (water
    and gas rates after breakthrough, GOR) it can rise for the truth itself; the whitened SSR
    weights each point by its noise, hence the decisive drop."""
    if n_heldout <= 0 or not (math.isfinite(e_after) and math.isfinite(ssr_after)):
        return False, False
    quiet = ssr_before <= heldout_noise_line(n_heldout, s)
    d = ssr_before - ssr_after
    ok = (e_after < e_before and (d > s.heldout_threshold or
                                  (quiet and d > -s.heldout_threshold))
          or (decisive and d > heldout_decisive_drop(n_heldout, s)
              and e_after < e_before * (1.0 + s.heldout_e_slack)))
    return bool(ok), bool(quiet)


# ----------------------------------------------------------------------------- the record
def record(ctx: Context, cal: Calibrated, c: Candidate, lm: LevenbergMarquardt,
           refined: LevenbergMarquardt | None, restart: dict, start: Run,
           line_search: list[dict], base_sc: dict) -> tuple[dict, Run]:
    """The record of candidate ``c`` recalibrated and its best run: the best of the warm start
    ``lm``, its refinement ``refined`` (when it fits better) and an accepted restart from the
    deck's values (``restart``: its record, :func:`hmcore.diagnosis.restart.restart`, which
    then replaces the warm start); judged by the fit line and the held-back rule against the
    calibrated model ``cal`` (``base_sc``: its :func:`hmcore.diagnosis.runs.run_scores`).
    ``start``: the run the warm start began at; ``line_search``: the points tried before."""
    s = ctx.settings
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
        # an accepted restart replaces the warm start, a refinement when it fits better
        if r.best is not None and (label != "refined" or
                                   r.best.payload.ssr_fit <= lm.best.payload.ssr_fit):
            reason, iters, lm = r.reason, iters + r.iteration, r
    run = lm.best.payload
    sc = run_scores(ctx.case, run) if run is not cal.run else base_sc
    d_fit = base_sc["ssr_fit"] - sc["ssr_fit"]
    d_ho = base_sc["ssr_heldout"] - sc["ssr_heldout"]
    e_ho_b, e_ho_a = base_sc["E_heldout"], sc["E_heldout"]
    line = fit_line(s, 2 if c.details.get("start_day") is not None else 1)
    fit_ok = d_fit > line
    ho_ok, quiet = heldout_confirms(base_sc["ssr_heldout"], sc["ssr_heldout"], e_ho_b, e_ho_a,
                                    cal.obs.n_noise("heldout"), s)
    value = run.values.get(c.name, c.neutral)
    eig = jtj_eigenvalues(lm.J)  # the fit's curvature: its Occam factor (evidence)
    out = {
        "start_value": start.values.get(c.name, c.neutral),
        "line_search": line_search,
        "id": c.id, "values": {c.name: c.neutral, **run.values},
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
        "jtj_eigenvalues": None if eig is None else [float(x) for x in eig],
        "per_well_response_after": sc["per_well_response"],
        "per_well_response_heldout_after": heldout_per_well(ctx.case, run.responses),
        "history": history}
    ctx.log(f"recalibrated {c.id}: SSR fit {base_sc['ssr_fit']:.1f} -> "
            f"{sc['ssr_fit']:.1f}, held-back {base_sc['ssr_heldout']:.1f} -> "
            f"{sc['ssr_heldout']:.1f}; E {base_sc['E']:.4g} -> {sc['E']:.4g}, "
            f"held-back E {e_ho_b:.4g} -> {e_ho_a:.4g}")
    return out, run
