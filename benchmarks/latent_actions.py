"""Latent actions against the ensemble smoother (issue 42): campaigns over the coefficients of
the fields' prior modes (``[latent]``, hmcore.fields.latent) on the hidden truths of
``benchmarks/ensemble_calibration.py``, judged like its ES-MDA runs.

    python benchmarks/latent_actions.py --out DIR --truths 1 2 3 \
        [--methods lm cmaes sac] [--seeds 1 2 3] [--share 0.9] [--max-modes 40] \
        [--budget N] [--draws 20] [--workers 2] [--max-minutes 120]

``DIR`` is the calibration benchmark's folder: its hidden truths ``DIR/truth-<s>`` (drawn
there by ``hmflow hide --kind field``, or here when missing, with ``--case``) and its store
``DIR/store``, where the ES-MDA runs ``t<s>-<variant>`` are. For each truth, method and seed,
one campaign ``t<s>-latent-<method>-s<seed>`` on a copy of the hidden case with a ``[latent]``
section (the same prior: ``[ensemble]`` size and seed), with

* **equal budget**: ES-MDA's simulations, ``size x (len(weights) + 1)`` (every member runs
  once per round and once more after the last update, which is its forecast), less the
  ``--draws`` that make the latent campaign's forecast (Laplace draws at the best call,
  :mod:`tasks.posterior`) and less one finite-difference run per coefficient, which those
  draws need at the best call when the method left no Jacobian there (CMA-ES, SAC, and lm
  when its best call stands on secant columns); the table counts every run in any journal of
  the campaign, so a campaign that needed none comes out under ES-MDA's count;
* the same judgement as ``reveal``'s: FOPT, FWPT, FGPT and each well's WOPT at the
  schedule's end against the forecast's P90-P10 (``inside_band``), and the RMSE to the truth
  of the mean field of the forecast's members (the posterior draws' fields; the best call's
  alone when none ran) against the prior mean's (``field_spread``).

Rows go to ``DIR/latent.csv`` (the calibration benchmark's columns, ``variant`` =
``latent-<method>``, ``seed``), ``DIR/latent_fields.csv`` and ``DIR/latent_runs.csv``
(simulations, wall time, best call, its chi2/n without the prior's term, E); the summary
printed sets them beside ES-MDA's rows of ``DIR/calibration.csv``. Everything resumes
(campaigns by their journals; a finished campaign is judged from the store). Nothing is
asserted.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tomlkit

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hmcore.calibration.objective import Objective  # noqa: E402
from hmcore.cases import load_case  # noqa: E402
from hmcore.fields.assimilation import draw_ensemble  # noqa: E402
from hmcore.fields.grid import read_grid  # noqa: E402
from hmcore.fields.latent import LatentBasis  # noqa: E402
from hmcore.fields.layout import Layout  # noqa: E402
from hmcore.fields.members import ensemble_matrix  # noqa: E402
from hmcore.fields.spread import field_spread  # noqa: E402
from hmcore.model.latent_case import latent_basis, latent_case  # noqa: E402
from hmcore.scenarios.field_truth import TRUTH_JSON, hide_field_truth  # noqa: E402
from hmcore.simulation.forecast import inside_band  # noqa: E402
from storage import ArtifactStore, EvaluationJournal  # noqa: E402
from hmflow.cli.flowrun import start_api  # noqa: E402
from storage.ensemble import ENSEMBLE_FILE, ensemble_step  # noqa: E402
from storage.latent import BASIS_DOC, BASIS_FILE, LATENT_STEP  # noqa: E402
from storage.posterior import POSTERIOR_STEP, journal_name  # noqa: E402


def latent_copy(hidden_case: Path, dest: Path, share: float, max_modes: int | None) -> Path:
    """The hidden case with a ``[latent]`` section, its deck and history by absolute path
    (rewritten only when it changes, so that a resumed campaign sees the same file)."""
    doc = tomlkit.parse(hidden_case.read_text())
    for key in ("deck", "observed"):
        doc["case"][key] = str((hidden_case.parent / doc["case"][key]).resolve())
    section = tomlkit.table()
    section["share"] = share
    if max_modes:
        section["max_modes"] = max_modes
    doc["latent"] = section
    dest.mkdir(parents=True, exist_ok=True)
    out, text = dest / "case.toml", tomlkit.dumps(doc)
    if not out.is_file() or out.read_text() != text:
        out.write_text(text)
    return out


def simulations(store: Path, campaign: str) -> int:
    """Every run journaled for the campaign: its calls, Jacobian runs and posterior draws."""
    return sum(1 for _ in (store / campaign).glob("evaluations*/*.json"))


def judge(truth: int, method: str, seed: int, case: Path, hidden: dict, store: ArtifactStore,
          campaign: str) -> tuple[list[dict], list[dict], dict]:
    """The campaign's forecast and fields against the truth (see the module's docstring)."""
    variant = f"latent-{method}"
    forecast = store.latest(campaign, "curves").read_parquet("forecast.parquet")
    checks = []
    for t in hidden["forecast"]:
        row = forecast[(forecast.well == t["well"]) & (forecast.quantity == t["quantity"])]
        if not len(row) or not np.isfinite(t["value"]):
            continue
        r = row.iloc[0]
        checks.append({"truth": truth, "variant": variant, "seed": seed,
                       "ensemble": "posterior", "well": t["well"], "quantity": t["quantity"],
                       "value": t["value"], "P90": r.P90, "P50": r.P50, "P10": r.P10,
                       "members": int(r.members),
                       "inside": inside_band(r.P90, r.P10, t["value"]),
                       "width": (r.P10 - r.P90) / abs(r.P50) if r.P50 else np.inf})
    version = store.latest(campaign, LATENT_STEP)
    doc = version.read_json(BASIS_DOC)
    basis = LatentBasis.from_table(version.read_parquet(BASIS_FILE), doc["share"],
                                   doc["available"])
    loaded = latent_case(load_case(case), basis)
    objective = Objective.of_case(loaded)
    plain = Objective(objective.name, objective.observations)
    best = store.latest(campaign, "report").read_json("report.json")["best"]
    best_record = EvaluationJournal(store, campaign).get(best["index"])
    members = [best_record]
    posterior = store.latest(campaign, POSTERIOR_STEP)
    if posterior is not None:
        draws = [r for r in EvaluationJournal(store, campaign, journal_name(posterior.version))
                 .rows() if r.get("status") == "COMPLETE"]
        members = draws if len(draws) >= 2 else members
    Z = np.array([[r["params"][n] for n in basis.names] for r in members], float)
    fields_now = np.stack([basis.fields(z) for z in Z])
    layout = Layout(tuple(f.name for f in loaded.fields), (), int(hidden["layout"]["n_active"]))
    truth_layout = Layout(tuple(hidden["layout"]["fields"]), tuple(hidden["layout"]["scalars"]),
                          int(hidden["layout"]["n_active"]))
    truth_x = ensemble_matrix(pd.read_parquet(hidden["truth_table"]), truth_layout)[0]
    prior_x = prior_members(store, hidden, campaign, layout, loaded)
    spaces = {f["name"]: f["space"] for f in hidden["fields"]}
    errors = []
    for name in layout.fields:
        s = field_spread(name, prior_x[:, layout.columns(name)],
                         fields_now[:, layout.columns(name)],
                         truth_x[truth_layout.columns(name)], spaces.get(name, ""))
        errors.append({"truth": truth, "variant": variant, "seed": seed, "field": name,
                       "rmse_prior": s.rmse_prior, "rmse_posterior": s.rmse_posterior,
                       "sd_prior": s.sd_prior, "sd_posterior": s.sd_posterior})
    run = {"truth": truth, "variant": variant, "seed": seed, "modes": basis.k,
           "share": basis.share, "simulations": simulations(store.root, campaign),
           "best_call": best["index"] + 1, "chi2_n": plain.likelihood(best_record),
           "objective": objective.likelihood(best_record), "E": best_record["E"],
           "forecast_members": len(members)}
    return checks, errors, run


def prior_members(store: ArtifactStore, hidden: dict, campaign: str, layout: Layout,
                  loaded) -> np.ndarray:
    """The prior ensemble's fields ``(N, p)``: the ES-MDA run's ``ensemble-00`` of this truth
    when stored (the same draw), else drawn again as the basis was."""
    for name in store.campaigns():
        if name.startswith(campaign.split("-latent-")[0] + "-") and "-latent-" not in name:
            version = store.latest(name, ensemble_step(0))
            if version is not None:
                meta = version.read_json("ensemble.json")
                full = Layout(tuple(meta["fields"]), tuple(meta["scalars"]),
                              int(meta["n_active"]))
                X = ensemble_matrix(version.read_parquet(ENSEMBLE_FILE), full)
                return np.concatenate([X[:, full.columns(f)] for f in layout.fields], axis=1)
    return draw_ensemble(loaded.fields, read_grid(loaded.deck), loaded.ensemble.size, (),
                         loaded.ensemble.seed).X


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--truths", type=int, nargs="+", required=True)
    ap.add_argument("--case", help="the field case, to draw a truth DIR does not hold")
    ap.add_argument("--methods", nargs="+", default=["lm", "cmaes", "sac"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--share", type=float, default=0.9)
    ap.add_argument("--max-modes", type=int, default=None)
    ap.add_argument("--budget", type=int, default=None,
                    help="calls per campaign (default: ES-MDA's simulations less --draws and "
                         "one run per mode)")
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-minutes", type=float, default=None)
    args = ap.parse_args()

    start_api()  # hmflow's: a SIGTERM to this group stops the run; logs drained at exit
    from flows.campaign import campaign_flow  # Prefect reads its API's URL on import

    started = time.time()
    out = args.out.resolve()
    store = ArtifactStore(out / "store")
    checks, errors, runs, skipped = [], [], [], []
    for s in args.truths:
        hidden_dir = out / f"truth-{s}"
        if not (hidden_dir / TRUTH_JSON).is_file():
            if not args.case:
                raise SystemExit(f"{hidden_dir} holds no hidden truth; give --case to draw it")
            hide_field_truth(load_case(args.case), hidden_dir, s)
        hidden = json.loads((hidden_dir / TRUTH_JSON).read_text())
        case = latent_copy(hidden_dir / "case.toml", out / "cases" / f"t{s}-latent",
                           args.share, args.max_modes)
        loaded = load_case(case)
        spec = loaded.ensemble
        modes = latent_basis(loaded, read_grid(loaded.deck)).k  # the Jacobian at the best call
        budget = args.budget or spec.size * (len(spec.weights) + 1) - args.draws - modes
        for method in args.methods:
            for seed in args.seeds:
                campaign = f"t{s}-latent-{method}-s{seed}"
                done = store.latest(campaign, "report") is not None
                if not done and args.max_minutes is not None and \
                        time.time() - started > 60 * args.max_minutes:
                    skipped.append(campaign)
                    continue
                if not done:
                    print(f"{campaign}: {budget} calls ({time.time() - started:.0f} s in)",
                          flush=True)
                    t0 = time.time()
                    result = campaign_flow(case=str(case), agent=method, budget=budget,
                                           workers=args.workers, seed=seed,
                                           storage=str(store.root), campaign=campaign,
                                           forecast_draws=args.draws)
                    if not isinstance(result, dict):
                        print(f"{campaign}: did not finish: {result}", flush=True)
                        continue
                    print(f"{campaign}: {time.time() - t0:.0f} s", flush=True)
                c, e, r = judge(s, method, seed, case, hidden, store, campaign)
                checks += c
                errors += e
                runs.append(r)
    if not runs:
        print("nothing judged yet")
        return
    pd.DataFrame(checks).to_csv(out / "latent.csv", index=False)
    pd.DataFrame(errors).to_csv(out / "latent_fields.csv", index=False)
    pd.DataFrame(runs).to_csv(out / "latent_runs.csv", index=False)
    print(summary(pd.DataFrame(checks), pd.DataFrame(errors), pd.DataFrame(runs),
                  out / "calibration.csv", out / "fields.csv", args.truths))
    if skipped:
        print(f"\nnot started (--max-minutes): {', '.join(skipped)}; run again to go on")


def summary(checks: pd.DataFrame, errors: pd.DataFrame, runs: pd.DataFrame, esmda_checks: Path,
            esmda_fields: Path, truths: list[int]) -> str:
    """Markdown: per variant (the latent methods over their seeds, ES-MDA's variants on the
    same truths), the share of truths inside the posterior's P10-P90 for FOPT and the wells'
    WOPT, the median relative width of FOPT's band, and the median RMSE of the mean fields
    to the truth; then the latent campaigns' costs."""
    tables = [checks]
    fields = [errors]
    if esmda_checks.is_file():
        e = pd.read_csv(esmda_checks)
        tables.append(e[(e.ensemble == "posterior") & e.truth.isin(truths)].assign(seed=0))
    if esmda_fields.is_file():
        f = pd.read_csv(esmda_fields)
        fields.append(f[f.truth.isin(truths)].assign(seed=0))
    allc, allf = pd.concat(tables, ignore_index=True), pd.concat(fields, ignore_index=True)
    lines = ["| variant | runs | FOPT inside | wells' WOPT inside | FWPT inside | FGPT inside | "
             "median FOPT width | median RMSE prior -> posterior (per field) |",
             "|---|---|---|---|---|---|---|---|"]
    for variant, g in allc.groupby("variant", sort=False):
        def share(mask) -> str:
            sub = g[mask]
            return f"{int(sub.inside.sum())} of {len(sub)}" if len(sub) else "-"
        fopt = g.quantity == "FOPT"
        rm = allf[allf.variant == variant].groupby("field")[["rmse_prior", "rmse_posterior"]]
        rmse = "; ".join(f"{k} {v.rmse_prior:.3g} -> {v.rmse_posterior:.3g}"
                         for k, v in rm.median().iterrows())
        lines.append(f"| {variant} | {g.groupby(['truth', 'seed']).ngroups} | {share(fopt)} | "
                     f"{share(g.quantity == 'WOPT')} | {share(g.quantity == 'FWPT')} | "
                     f"{share(g.quantity == 'FGPT')} | {g[fopt].width.median():.3f} | {rmse} |")
    lines += ["", "| variant | campaigns | modes | median simulations | median chi2/n of the "
              "best call | median best call |", "|---|---|---|---|---|---|"]
    for variant, g in runs.groupby("variant", sort=False):
        lines.append(f"| {variant} | {len(g)} | {int(g.modes.median())} | "
                     f"{int(g.simulations.median())} | {g.chi2_n.median():.3g} | "
                     f"{int(g.best_call.median())} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
