"""The restart: the best recalibrated candidates recalibrated again from the deck's values.

A global parameter at its bound has absorbed what it could of a missing effect; with the right
extension its best value is usually back inside, but the warm-started recalibration starts in
the absorbed basin and its linear model points along the bound. A fit that the held-back
history vetoes has often stayed in such a basin without a bound. So, when the calibration left
globals at (within ``near_bound`` of) their bounds, the best warm fits
(:func:`hmcore.diagnosis.refit.restart_choice`) are restarted; otherwise
(``restart_on_veto``) the best fits that the held-back history does not plainly confirm
(:func:`hmcore.diagnosis.refit.veto_restart_choice`).

A restart puts the globals at the deck's values and tries the candidate alone there
(``restart_grid`` and its recalibrated value: does the extension alone explain the data on the
model as given?), then from the best of those minimises the fitted SSR plus a Gaussian prior
on the globals (``restart_prior_sd``), fresh finite-difference Jacobian. Its result replaces
the warm start's only when

(a) its SSR + prior is lower than the warm start's and its fitted SSR at most
    ``restart_slack`` higher (of fits the data cannot tell apart, the one closer to the model
    as given), and
(b) the restart's globals with the candidate neutral fit worse than the calibrated model
    (otherwise the calibration, not the candidate, was short of its minimum, and the gain
    would be the globals'; a well's own skin is neutral at the global skin of the restart's
    point): one check run each.

The numerics (choice, grid, prior, evaluations per restart) are :mod:`hmcore.diagnosis.refit`'s;
this module makes the runs through the round's :class:`hmcore.diagnosis.runs.Simulations`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hmcore.diagnosis import refit
from hmcore.diagnosis.confirmation import heldout_confirms
from hmcore.diagnosis.candidate import current_skin
from hmcore.model.deck_values import base_values
from hmcore.diagnosis.recalibrate import Coordinates, LevenbergMarquardt, Point, run_lockstep
from hmcore.diagnosis.runs import run_scores
from hmcore.diagnosis.state import Calibrated, Context, Ranking


def globals_at_bounds(ctx: Context, cal: Calibrated) -> list[str]:
    """The globals the calibration left within ``near_bound`` (scaled) of a bound."""
    return [n for n, u in zip(ctx.coords.names, cal.u)
            if abs(u) >= 1.0 - ctx.settings.near_bound]


def restart(ctx: Context, cal: Calibrated, ranking: Ranking, ids: list[str],
            minimisers: list[LevenbergMarquardt], refined: dict[int, LevenbergMarquardt],
            coords: list[Coordinates]) -> dict[str, dict]:
    """Restart the chosen recalibrations (``ids[k]``: candidate of ``minimisers[k]``, its
    refinement ``refined[k]``, its extended model's coordinates ``coords[k]``: the globals,
    then the candidate). Returns, per restarted candidate id, its record (``minimiser``,
    ``runs``, ``grid``, ``globals_at_bounds``, ``trigger``, ``ssr_fit``, ``ssr_heldout``,
    ``prior``, ``values``, ``ssr_fit_warm``, ``prior_warm``, ``ssr_fit_neutral``,
    ``accepted``, ``reason``); empty when nothing is restarted."""
    s = ctx.settings
    at_bound = globals_at_bounds(ctx, cal)
    if not ids or (not at_bound and not s.restart_on_veto):
        return {}
    warm = {k: min([x.best for x in (m, refined.get(k)) if x is not None and x.best is not None],
                   key=lambda b: b.ssr, default=None) for k, m in enumerate(minimisers)}
    chosen, trigger = _choose(ctx, cal, ids, warm, at_bound)
    if not chosen:
        return {}
    start_globals = ctx.coords.to_u(base_values(ctx.case.info, ctx.case.space))
    settings = s.restart
    if s.budget is not None:
        per = refit.restart_evaluations(ctx.sims.left(), len(chosen), len(s.restart_grid),
                                        ctx.coords.dim)
        if per is None:
            ctx.log(f"restart skipped: {ctx.sims.left()} simulator calls left")
            return {}
        settings = refit.capped(settings, per)
    ctx.log(f"restart from the deck's values: {trigger}")
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
    grid_runs = ctx.sims.run(ranking.union_case, jobs, "restart-grid", cal.obs)
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
        runs = ctx.sims.run(ranking.union_case, [coords[k].to_values(u) for k, u in batch],
                            "restart", cal.obs)
        return [(prior.extend(u, run.r_fit), run) for (_, u), run in zip(batch, runs)]

    order = list(restarts)
    run_lockstep([restarts[k] for k in order],
                 lambda batch: evaluate([(order[j], u) for j, u in batch]), s.workers,
                 limit=ctx.sims.left(len(chosen)))  # one check run each kept back
    by_id = {c.id: c for c in ranking.candidates}
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
            neutral[c.name] = (current_skin(c.wells[0], ctx.case.space, neutral, ctx.case.info)
                               if c.kind == "well_skin" else c.neutral)
            checks.append((cid, neutral))
        out[cid] = rec
    _check(ctx, cal, ranking, out, checks)
    return out


def _choose(ctx: Context, cal: Calibrated, ids: list[str], warm: dict[int, Point | None],
            at_bound: list[str]) -> tuple[list[int], str]:
    """Which recalibrations to restart (indices, best fits first) and why, in words."""
    s = ctx.settings
    warm_ssr = {k: w.ssr for k, w in warm.items() if w is not None}
    if at_bound:
        return (refit.restart_choice(warm_ssr, cal.run.ssr_fit, s),
                f"globals {at_bound} were at their bounds")
    base_sc = run_scores(ctx.case, cal.run)
    n_ho = cal.obs.n_noise("heldout")

    def confirms(k: int) -> bool:
        # plainly (E and SSR both drop): a fit whose held-back E rises is restarted even when
        # its SSR drops decisively
        return heldout_confirms(base_sc["ssr_heldout"], warm[k].payload.ssr_heldout,
                                base_sc["E_heldout"],
                                run_scores(ctx.case, warm[k].payload)["E_heldout"], n_ho, s,
                                decisive=False)[0]

    chosen = refit.veto_restart_choice(warm_ssr, {k: confirms(k) for k in warm_ssr},
                                       cal.run.ssr_fit, s)
    return chosen, ("the best fit(s) " + ", ".join(ids[k] for k in chosen)
                    + " do not plainly predict the held-back history better than the "
                      "calibrated model (held-back E and SSR both lower)")


def _check(ctx: Context, cal: Calibrated, ranking: Ranking, out: dict[str, dict],
           checks: list[tuple[str, dict[str, float]]]) -> None:
    """Condition (b): each restart that beat its warm start, run again with the candidate
    neutral; accepted when that fits worse than the calibrated model. Completes ``out``."""
    runs = ctx.sims.run(ranking.union_case, [v for _, v in checks], "restart-check", cal.obs)
    for (cid, _), run in zip(checks, runs):
        rec = out[cid]
        rec["runs"] += 1
        rec["ssr_fit_neutral"] = run.ssr_fit
        rec["accepted"] = bool(run.ok and run.ssr_fit >= cal.run.ssr_fit)
        rec["reason"] = ("as good a fit as the warm start or better, closer to the deck's "
                         "values, and only with the candidate" if rec["accepted"] else
                         "rejected: the restart's globals fit better than the calibration "
                         "even with the candidate neutral (the gain would be the globals')")
        ctx.log(f"restart {cid}: SSR fit {rec['ssr_fit']:.1f} + prior {rec['prior']:.1f} "
                f"(warm {rec['ssr_fit_warm']:.1f} + {rec['prior_warm']:.1f},"
                f" candidate neutral {run.ssr_fit:.1f}, base {cal.run.ssr_fit:.1f}): "
                f"{'accepted' if rec['accepted'] else 'rejected'}")
