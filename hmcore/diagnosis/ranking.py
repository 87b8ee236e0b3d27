"""Step 3 of a diagnosis: every candidate extension ranked by a score test at the calibrated
point.

One batch of runs: a probe per candidate of the library, and a finite difference per global
parameter when the calibration left no Jacobian of the globals close enough to reuse
(:func:`hmcore.diagnosis.screening.probe_jobs`); the score tests with the globals projected
out (:func:`hmcore.diagnosis.screening.screen`). Then probes of what that batch points to, all
ranked together with the library's:

- dated productivity changes, from the well-skin probes (:mod:`hmcore.diagnosis.dating`);
- the boxes of the strongest regional candidates moved beside their wells
  (:func:`hmcore.diagnosis.extensions.shifted_regions`), when the budget leaves room.
"""

from __future__ import annotations

import numpy as np

from hmcore.diagnosis import dating, screening
from hmcore.diagnosis.attribution import projector_basis
from hmcore.diagnosis.candidate import Candidate, extended_space
from hmcore.diagnosis.extensions import build_candidates, dated_productivity, shifted_regions
from hmcore.diagnosis.state import Calibrated, Context, Ranking
from hmcore.ordering import natural_key


def rank(ctx: Context, cal: Calibrated) -> Ranking:
    """Probe and score every candidate at the calibrated model ``cal``. ValueError when the
    budget left cannot cover the probes (the calibration sets them aside: a bug)."""
    s, case, sims = ctx.settings, ctx.case, ctx.sims
    values0 = cal.run.values
    candidates = build_candidates(case.info, case.space, values0, s.kinds)
    union_case = case.with_space(extended_space(case.space, candidates))
    jobs = screening.probe_jobs(ctx.coords, cal.u, values0, candidates, cal.jacobian is None,
                                s.global_fd_step)
    left = sims.left()
    if left is not None and len(jobs) > left:  # set aside by the calibration: a bug
        raise ValueError(f"budget {s.budget} leaves {left} simulator calls after the "
                         f"calibration, but the ranking needs {len(jobs)}")
    runs = sims.run(union_case, [j.values for j in jobs], "ranking", cal.obs)
    r0 = cal.run.r_fit
    residuals = [run.r_fit for run in runs]
    J_global = (cal.jacobian if cal.jacobian is not None else
                screening.global_jacobian(r0, jobs, residuals, ctx.coords.dim))
    held = screening.held_at_bounds(J_global, r0, cal.u)
    result = screening.screen(candidates, jobs, residuals,
                              [getattr(run.result, "reason", "") for run in runs], r0,
                              J_global, held, ctx.coords.names, s)
    datings, dated = _date(ctx, cal, result, J_global, held)
    shifted = _shifted(ctx, candidates, result, len(dated))
    for added, step in ((dated, "dating"), (shifted, "region-shifts")):
        if not added:  # their probes, then the ranking of them all
            continue
        candidates = candidates + added
        union_case = case.with_space(extended_space(case.space, candidates))
        more = screening.probe_jobs(ctx.coords, cal.u, values0, added, False, s.global_fd_step)
        jobs, runs = jobs + more, runs + sims.run(union_case, [j.values for j in more], step,
                                                  cal.obs)
    if dated or shifted:
        residuals = [run.r_fit for run in runs]
        result = screening.screen(candidates, jobs, residuals,
                                  [getattr(run.result, "reason", "") for run in runs], r0,
                                  J_global, held, ctx.coords.names, s)
    probe_runs = {j.candidate.id: run for j, run in zip(jobs, runs) if j.candidate}
    result.document["dating"] = [d.to_dict() for d in datings]
    order, beyond = result.document["order"], result.document["beyond_noise"]
    top = ", ".join(f"{k} ({result.scores[k].chi2:.0f})" for k in order[:5])
    ctx.log(f"ranking: {len(beyond)} of {len(order)} candidates beyond noise "
            f"({len(result.document['screened'])} screened for recalibration); top: {top}")
    return Ranking(tuple(candidates), union_case, result.scores, result.sensitivity,
                   probe_runs, J_global, held, result.document)


def _shifted(ctx: Context, candidates: list[Candidate], result: screening.Screening,
             reserved: int) -> list[Candidate]:
    """The moved boxes of the strongest regional candidates beyond noise (at most
    ``settings.region_shifts`` wells, the strongest first), as many wells' as the budget
    leaves room for besides ``reserved`` other probes and a first step of the
    recalibration (a finite difference per parameter for ``confirm_top`` candidates)."""
    s, case = ctx.settings, ctx.case
    if "regional_permeability" not in s.kinds or s.region_shifts < 1:
        return []
    by_id = {c.id: c for c in candidates}
    regional = [k for k in result.document["beyond_noise"]
                if by_id[k].kind == "regional_permeability" and "shift" not in
                by_id[k].details][: s.region_shifts]
    taken = [tuple(c.parameter.box) for c in candidates
             if c.kind == "regional_permeability" and c.parameter.box]
    left = ctx.sims.left(reserved + s.confirm_top * (ctx.coords.dim + 2))
    out: list[Candidate] = []
    for k in regional:
        moved = [c for c in shifted_regions(case.info, by_id[k].wells[0], taken)
                 if c.name not in case.space.names]
        if left is not None and len(out) + len(moved) > left:
            ctx.log(f"ranking: the moved boxes beside {by_id[k].wells[0]} not probed: "
                    f"{len(moved)} runs, {max(left - len(out), 0)} left of the budget "
                    "after the recalibration's first step")
            break
        taken += [tuple(c.parameter.box) for c in moved]
        out += moved
    if out:
        ctx.log(f"ranking: {len(out)} moved boxes beside "
                f"{', '.join(sorted({c.wells[0] for c in out}, key=natural_key))}")
    return out


def _date(ctx: Context, cal: Calibrated, result: screening.Screening, J_global: np.ndarray,
          held: np.ndarray) -> tuple[list[dating.Dating], list[Candidate]]:
    """The date scans of the wells (``productivity_change``), from their well-skin
    probes, and the dated candidates they justify (:mod:`hmcore.diagnosis.dating`)."""
    s, case, obs = ctx.settings, ctx.case, cal.obs
    if "productivity_change" not in s.kinds:
        return [], []
    r0 = cal.run.r_fit
    idx = obs.vector_index("fit")
    days = obs.rows.days.to_numpy(float)[idx]
    wells = obs.rows.well.to_numpy()[idx]
    Q = projector_basis(J_global[:, ~held])
    scans = {}
    for well in sorted(case.info.producers, key=natural_key):
        j = result.sensitivity.get(f"well_skin:{well}")
        if j is not None:
            scans[well] = (j, dating.scan_days(case.info.report_days, days,
                                               wells == well, s.dating_min_after))
    n_tests = sum(len(d) for _, d in scans.values())
    datings = [dating.date_well(w, r0, j, days, Q, tried, s.dating_alpha, n_tests)
               for w, (j, tried) in scans.items()]
    chosen = dating.choose(datings, s.dated_max)
    if datings:
        ctx.log("dating: " + ", ".join(
            f"{d.well} day {d.day:g} (+{d.gain:.0f} vs {d.threshold:.1f})"
            for d in sorted(datings, key=lambda d: -d.gain)[:3]))
    dated = [dated_productivity(case.info, d.well, d.day) for d in chosen]
    return datings, [c for c in dated if c.name not in case.space.names]
