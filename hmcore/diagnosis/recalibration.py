"""Steps 4 and 5 of a diagnosis: the extended models of the leading candidates, recalibrated.

4. :func:`extend` - which screened candidates to recalibrate
   (:func:`hmcore.diagnosis.screening.confirm_choice`; a well's regional boxes are
   near-alternatives, so at most :data:`REGIONS_PER_WELL` of them go on), each model the
   globals + the candidate's parameter. No simulation.
5. :func:`recalibrate` - each model warm-started at the calibrated point: a short line search
   along the linear model's joint direction chooses the start (:func:`line_search`), then the
   models are recalibrated together (lockstep Levenberg-Marquardt, Broyden Jacobian updates);
   the best fits beyond noise continue from a fresh finite-difference Jacobian; some are
   restarted from the deck's values (:mod:`hmcore.diagnosis.restart`); each is judged by the
   fit line and the held-back rule (:func:`hmcore.diagnosis.confirmation.record`).
"""

from __future__ import annotations

import numpy as np

from hmcore.diagnosis import refit, restart, screening
from hmcore.diagnosis.confirmation import fit_line, record
from hmcore.diagnosis.candidate import extended_space
from hmcore.diagnosis.recalibrate import Coordinates, LevenbergMarquardt, Point, run_lockstep
from hmcore.diagnosis.runs import Run, run_scores
from hmcore.diagnosis.state import Calibrated, Context, Extension, Ranking, Recalibration

REGIONS_PER_WELL = 2
"""Regional boxes of one well (centred or moved) recalibrated at most: the best two by chi2."""


def extend(ctx: Context, cal: Calibrated, ranking: Ranking) -> Extension:
    """The extended models of the leading candidates (no simulation)."""
    by_id = {c.id: c for c in ranking.candidates}
    screened, per_well = [], {}
    for k in ranking.document["screened"]:  # best first; a well's boxes are near-alternatives:
        c = by_id[k]  # its best two go on, so that they do not fill every slot
        if c.kind == "regional_permeability":
            per_well[c.wells] = per_well.get(c.wells, 0) + 1
            if per_well[c.wells] > REGIONS_PER_WELL:
                continue
        screened.append(k)
    top = screening.confirm_choice([(k, ranking.scores[k].chi2) for k in screened],
                                   ctx.settings)
    models = []
    for cid in top:
        c = by_id[cid]
        space = extended_space(ctx.case.space, [c])
        models.append({"id": cid, "kind": c.kind, "description": c.description,
                       "parameters": [p.model_dump(mode="json") for p in space.parameters],
                       "start": {**cal.run.values, c.name: c.neutral},
                       "predicted_value": next(r["predicted_value"]
                                               for r in ranking.document["candidates"]
                                               if r["id"] == cid)})
    return Extension(tuple(m["id"] for m in models), {
        "models": models,
        "note": ("no candidate explains more than noise: nothing to extend" if not models else
                 f"{len(models)} leading candidate(s) to recalibrate")})


def recalibrate(ctx: Context, cal: Calibrated, ranking: Ranking,
                extension: Extension) -> Recalibration:
    """Recalibrate every model of ``extension`` (see the module docstring) within the budget
    left, and judge each against the calibrated model."""
    s, sims, union_case = ctx.settings, ctx.sims, ranking.union_case
    ids = list(extension.ids)
    starts, searched = line_search(ctx, cal, ranking, ids)
    lm_settings = s.recalibration
    if s.budget is not None and ids:
        lm_settings = refit.capped(lm_settings, sims.left() // len(ids))
    by_id = {c.id: c for c in ranking.candidates}
    minimisers, coords = [], []
    for cid in ids:
        u0, run0 = starts[cid]
        J0 = np.column_stack([ranking.jacobian, ranking.sensitivity[cid]])
        minimisers.append(LevenbergMarquardt(u0, lm_settings,
                                             start=Point(u0.copy(), run0.r_fit, run0),
                                             jacobian=J0, label=cid))
        coords.append(Coordinates(extended_space(ctx.case.space, [by_id[cid]]).parameters))

    def evaluate(batch):
        values = [coords[k].to_values(u) for k, u in batch]
        runs = sims.run(union_case, values, "recalibration", cal.obs)
        return [(run.r_fit, run) for run in runs]

    run_lockstep(minimisers, evaluate, s.workers, limit=sims.left())
    # the contenders (best fits, each beyond noise) continue from a fresh finite-difference
    # Jacobian: Broyden's updates stall in the curved valleys the globals make
    contenders = sorted((k for k, m in enumerate(minimisers) if m.best is not None
                         and cal.run.ssr_fit - m.best.ssr > s.fit_threshold),
                        key=lambda k: minimisers[k].best.ssr)[: s.refine_top]
    refine_settings = s.refine
    if s.budget is not None and contenders:
        left = sims.left() // len(contenders)
        refine_settings = refit.capped(refine_settings, left)
        contenders = contenders if left > len(ctx.coords.names) + 1 else []
    refined = {k: LevenbergMarquardt(minimisers[k].best.u, refine_settings,
                                     start=minimisers[k].best, label=f"{ids[k]} (refined)")
               for k in contenders}
    if refined:
        keys = list(refined)
        run_lockstep([refined[k] for k in keys],
                     lambda batch: evaluate([(keys[j], u) for j, u in batch]), s.workers,
                     limit=sims.left())
    restarts = restart.restart(ctx, cal, ranking, ids, minimisers, refined, coords)
    base_sc = run_scores(ctx.case, cal.run)
    confirmed, runs = {}, {}
    for k, (cid, lm) in enumerate(zip(ids, minimisers)):
        c = next(x for x in ranking.candidates if x.id == cid)
        confirmed[cid], runs[cid] = record(ctx, cal, c, lm, refined.get(k),
                                           restarts.get(cid, {}), starts[cid][1],
                                           searched.get(cid, []), base_sc)
    return Recalibration(confirmed, runs, {"confirmed": confirmed, "thresholds": {
        "fit": s.fit_threshold, "fit_dated": fit_line(s, 2),
        "heldout": s.heldout_threshold}})


def line_search(ctx: Context, cal: Calibrated, ranking: Ranking, ids: list[str]
                ) -> tuple[dict[str, tuple[np.ndarray, Run]], dict[str, list[dict]]]:
    """Start points of the recalibrations (scaled coordinates: globals + the candidate), and
    per candidate the points tried (value, fitted SSR, globals).

    For each candidate, the best of the calibrated model, its probe run, and runs at the
    multiples ``settings.line_search`` of the score test's linear step along the joint
    direction the linear model gives (:func:`hmcore.diagnosis.refit.joint_direction`: the
    candidate moves, the free globals undo what they had absorbed of it). A response that
    bends (an aquifer's strength, a baffle, a layer that stops flowing) can put that step out
    of reach of a warm-started LM whose first steps trust the linear model only near the
    start. The runs are skipped when the budget left cannot also cover the recalibrations
    (:func:`hmcore.diagnosis.refit.line_search_affordable`)."""
    s = ctx.settings
    by_id = {c.id: c for c in ranking.candidates}
    searched: dict[str, list[dict]] = {}
    starts: dict[str, tuple[np.ndarray, Run]] = {}
    jobs, tags = [], []
    free = ~ranking.held
    for cid in ids:
        c = by_id[cid]
        cc = Coordinates([c.parameter])
        u0 = float(cc.to_u({c.name: c.neutral})[0])
        u_probe = float(cc.to_u({c.name: c.probe})[0])
        base_u = np.concatenate([cal.u, [u0]])
        points = [(base_u, cal.run),
                  (np.concatenate([cal.u, [u_probe]]), ranking.probe_runs.get(cid))]
        starts[cid] = min(((u, r) for u, r in points if r is not None and r.ok),
                          key=lambda ur: ur[1].ssr_fit)
        direction = refit.joint_direction(ranking.jacobian, free, ranking.sensitivity[cid])
        co = Coordinates(extended_space(ctx.case.space, [c]).parameters)
        for u in refit.line_search_points(base_u, ranking.scores[cid].step_u, direction,
                                          s.line_search, [u for u, _ in points]):
            jobs.append(co.to_values(u))
            tags.append((cid, u))
    if not refit.line_search_affordable(ctx.sims.left(), len(jobs), len(ids), ctx.coords.dim):
        return starts, searched
    for (cid, u), run in zip(tags, ctx.sims.run(ranking.union_case, jobs, "line-search",
                                                cal.obs)):
        c = by_id[cid]
        searched.setdefault(cid, []).append(
            {"value": run.values[c.name], "ssr_fit": run.ssr_fit,
             "globals": {n: run.values[n] for n in ctx.coords.names}})
        if run.ok and run.ssr_fit < starts[cid][1].ssr_fit:
            starts[cid] = (u, run)
    return starts, searched
