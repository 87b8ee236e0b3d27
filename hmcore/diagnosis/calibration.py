"""Step 1 of a diagnosis: the calibrated model and the noise model of its residuals.

The case's own (global) parameters are calibrated by the bounded Levenberg-Marquardt of
:mod:`hmcore.diagnosis.recalibrate` on whitened residuals, or a given calibrated vector (a
campaign's best, or round 1's recalibrated model) is simulated once:

- phase 1: weighted least squares (sigma from the data or estimated from the observed series,
  no time correlation) from the deck's values;
- then the noise level and its time correlation are re-estimated from the residuals of that
  model (:meth:`hmcore.scoring.observations.ObservationSet.refine`);
- phase 2 polishes the fit under that noise model (fresh finite-difference Jacobian,
  prewhitened residuals).

With a budget, the ranking's calls are set aside first
(:func:`hmcore.diagnosis.budget.ranking_reserve`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from hmcore.diagnosis.budget import budget_problem, ranking_reserve
from hmcore.model.deck_values import base_values
from hmcore.diagnosis.recalibrate import LevenbergMarquardt, LMSettings, Point, run_lockstep
from hmcore.diagnosis.runs import Run, rescore, run_scores
from hmcore.diagnosis.state import Calibrated, Context
from hmcore.scoring.observations import ObservationSet


def calibrate(ctx: Context, calibrated: dict[str, float] | None = None,
              initial: dict[str, float] | None = None, result: Any = None) -> Calibrated:
    """Calibrate the case's parameters from ``initial`` (default: the base model as given,
    :func:`hmcore.model.deck_values.base_values`), or start from ``calibrated``: phase 1 is
    then skipped, phase 2 still polishes it unless ``settings.polish_given`` is off.

    A budget that cannot cover :func:`hmcore.diagnosis.budget.minimum_runs` is refused
    (ValueError) before any simulation. ``result``: the simulation of ``calibrated`` when it
    was already made (a second round starts from the first's recalibrated model), so it is
    not run again. RuntimeError when the calibrated model fails to simulate."""
    case, s, sims, coords = ctx.case, ctx.settings, ctx.sims, ctx.coords
    space = case.space
    problem = budget_problem(case, s, calibrated is not None, "budget")
    if problem:
        raise ValueError(str(problem))
    reserve = ranking_reserve(case, s) if s.budget is not None else 0
    obs0 = ctx.obs
    phases = []
    if calibrated is not None:
        missing = [n for n in space.names if n not in calibrated]
        if missing:
            raise KeyError(f"calibrated values miss parameters {missing}")
        values = {n: float(calibrated[n]) for n in space.names}
        run = (rescore(Run(values, result, None, None), obs0) if result is not None
               else sims.run(case, [values], "calibration", obs0)[0])
        if not run.ok:
            raise RuntimeError(f"the calibrated model failed to simulate: "
                               f"{getattr(run.result, 'reason', '')}")
        phases.append({"phase": "given", "runs": 0 if result is not None else 1})
    else:
        start = {**base_values(case.info, space), **(initial or {})}
        wls = obs0.without_time_correlation()
        lm = _minimise(ctx, LevenbergMarquardt(coords.to_u(start),
                                               _capped(ctx, s.calibration, 0.3),
                                               label="phase 1"), wls, reserve)
        run = lm.best.payload
        phases.append(lm_document("1: weighted least squares, noise from the observed "
                                  "series", lm, start))
    # the noise model from the residuals of the calibrated model
    obs = obs0.refine(run.responses, case.observed)
    run = rescore(run, obs)
    u = coords.to_u(run.values)
    jacobian = None
    left = sims.left(reserve)
    if (calibrated is None or s.polish_given) and (left is None or left >= coords.dim + 1):
        lm = _minimise(ctx, LevenbergMarquardt(u, _capped(ctx, s.polish, 0.15),
                                               start=Point(u, run.r_fit, run),
                                               label="phase 2"), obs, reserve)
        run, u = lm.best.payload, lm.best.u
        if lm.J_fd is not None and np.max(np.abs(lm.u_fd - u)) <= s.reuse_jacobian_within:
            jacobian = lm.J_fd  # close enough to the final point: no new differences
        phases.append(lm_document("2: prewhitened residuals, noise from the residuals",
                                  lm, None))
    elif calibrated is None or s.polish_given:
        phases.append({"phase": "2: skipped, the budget is kept for the ranking", "runs": 0})
    method = {"method": ("levenberg-marquardt" if calibrated is None else
                         "given, polished" if s.polish_given else "given"),
              "runs": sum(p["runs"] for p in phases), "phases": phases,
              "noise_initial": obs0.noise_report, "noise": obs.noise_report}
    sc = run_scores(case, run)
    document = {"values": run.values, "u": u.tolist(), **method, **sc,
                "parameters": [p.model_dump(mode="json") for p in space.parameters],
                "n_fit": obs.n_fit, "n_heldout": obs.n_heldout,
                "history_end_days": obs.history_end_days}
    ctx.log(f"calibrated: E = {sc['E']:.5g}, held-back E = {sc['E_heldout']:.5g}, "
            f"SSR fit {sc['ssr_fit']:.1f} over {obs.n_fit} points")
    return Calibrated(run, u, obs, jacobian, document)


def _capped(ctx: Context, lm: LMSettings, share: float) -> LMSettings:
    """``lm`` with its evaluations capped to ``share`` of the budget (when one is set)."""
    if ctx.settings.budget is None:
        return lm
    cap = max(ctx.coords.dim + 3, int(share * ctx.settings.budget))
    return dataclasses.replace(lm, max_evaluations=min(lm.max_evaluations, cap))


def _minimise(ctx: Context, lm: LevenbergMarquardt, obs: ObservationSet,
              reserve: int) -> LevenbergMarquardt:
    """Run ``lm`` on the globals, residuals whitened under ``obs``, leaving ``reserve`` calls
    of the budget. RuntimeError when not even its start point simulates."""
    def evaluate(batch):
        runs = ctx.sims.run(ctx.case, [ctx.coords.to_values(u) for _, u in batch],
                            "calibration", obs)
        return [(run.r_fit, run) for run in runs]

    run_lockstep([lm], evaluate, limit=ctx.sims.left(reserve))
    if lm.best is None:
        raise RuntimeError(f"calibration failed: {lm.reason}")
    return lm


def lm_document(phase: str, lm: LevenbergMarquardt, start: dict | None) -> dict:
    """A minimisation as ``calibration.json`` records it: runs, iterations, why it stopped,
    the start values, the final SSR and the history of its steps."""
    return {"phase": phase, "runs": lm.n_evaluations, "iterations": lm.iteration,
            "stopped": lm.reason, "start": start, "ssr": lm.best.ssr,
            "history": [dataclasses.asdict(h) for h in lm.history]}
