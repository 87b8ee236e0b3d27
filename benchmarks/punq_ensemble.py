"""PUNQ-S3 as the literature runs it: the ensemble run judged against the truth, which is the
deck's own fields (issue 41).

    python benchmarks/punq_ensemble.py --out bench-punq-ensemble \
        [--case benchmarks/cases/punqs3_fields.toml] [--campaign punq-es] [--workers 2] \
        [--set localisation=distance --set radius=1500] [--evaluate-only]

1. The truth, once: ``OUT/truth/hidden_truth.json`` as ``hmflow hide --kind field`` writes it
   (so ``hmflow reveal`` reads it): the deck's own PORO, PERMX and PERMZ in update space
   (``truth.parquet``, read with opm.io), and the forecast quantities of one run of the deck
   as it is (FOPT, FWPT, FGPT, each well's WOPT at the schedule's end; PUNQ-S3's truth FOPT
   at day 6025 is 3.882e6 sm3). The truth is read after the run, never by it.
2. The run: ``hmflow ensemble --case OUT/case-NAME/case.toml --campaign NAME --storage
   OUT/store --workers W``, on a copy of CASE (``--set key=value`` changes its ``[ensemble]``
   section) with the truth's ``hidden_truth.json`` beside it, so that the report draws the
   truth in its forecast fans and layer maps. It resumes: started again, it simulates only
   the members not journaled.
3. The judgement, from stored artifacts only (``hmflow reveal``'s): the truth's FOPT and
   each well's WOPT against the prior's and the posterior's P10-P90, the band widths, the RMSE
   of the prior's and the posterior's mean fields to the truth per field and per layer, the
   mean spread of the members, the misfit per round; and the run's cost: its wall time
   against the simulator time per worker (sum of the members' simulator seconds / W), and the
   updates' seconds. Printed as Markdown and written to ``OUT/<campaign>.json``.

Nothing is asserted; the figures go into docs/ensembles.md and docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tomlkit

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ensemble_calibration import case_copy  # noqa: E402  (benchmarks/, the script's folder)
from hmcore.cases import load_case  # noqa: E402
from hmcore.fields.ensemble import EnsembleSpec  # noqa: E402
from hmcore.fields.grdecl import write_grdecl  # noqa: E402
from hmcore.fields.grid import read_grid  # noqa: E402
from hmcore.fields.layout import Layout  # noqa: E402
from hmcore.fields.members import ensemble_matrix, ensemble_table  # noqa: E402
from hmcore.fields.spread import kept  # noqa: E402
from hmcore.fields.transform import to_update_space  # noqa: E402
from hmcore.scenarios.field_truth import (  # noqa: E402
    FIELD_KIND,
    TRUTH_JSON,
    TRUTH_TABLE,
    reveal_field_truth,
    truth_forecast,
)
from hmcore.scoring.evaluation import evaluate, simulator_for  # noqa: E402
from hmcore.simulation.curves import read_curves  # noqa: E402
from storage import ArtifactStore, EvaluationJournal  # noqa: E402
from storage.ensemble import (  # noqa: E402
    ENSEMBLE_DOC,
    ENSEMBLE_FILE,
    FORECAST_STEP,
    ensemble_step,
    member_journal,
)

DEFAULT_CASE = REPO / "benchmarks" / "cases" / "punqs3_fields.toml"


TRUTH_GRDECL = "truth.GRDECL"
"""The truth's fields as the report reads them (physical values per active cell)."""


def write_truth_grdecl(case, grid, out: Path) -> Path:
    """``out/truth.GRDECL``: the deck's own values of every field's keyword."""
    return write_grdecl(out / TRUTH_GRDECL, {f.keyword: grid.deck_values(f.keyword)
                                             for f in case.fields},
                        header="-- the deck's own fields: PUNQ-S3's truth")


def write_deck_truth(case_path: Path, out: Path) -> Path:
    """``out/hidden_truth.json`` for a case whose truth is its deck's own fields; kept when
    it exists (the truth's GRDECL added to one written before it was)."""
    doc_path = out / TRUTH_JSON
    if doc_path.is_file():
        doc = json.loads(doc_path.read_text())
        if not doc.get("truth_grdecl"):
            case = load_case(case_path)
            doc["truth_grdecl"] = str(write_truth_grdecl(case, read_grid(case.deck), out))
            doc_path.write_text(json.dumps(doc, indent=2) + "\n")
        return doc_path
    out.mkdir(parents=True, exist_ok=True)
    case = load_case(case_path)
    grid = read_grid(case.deck)
    layout = Layout(tuple(f.name for f in case.fields), (), grid.n_active)
    X = layout.stack({f.name: to_update_space(grid.deck_values(f.keyword), f)[None, :]
                      for f in case.fields})
    ensemble_table(X, layout).to_parquet(out / TRUTH_TABLE)
    whole = case.simulator.model_copy(update={"stop_at_last_observation": False})
    plain = type(case)(**{**case.__dict__, "simulator": whole})
    run_dir = out / "truth-run"
    ev = evaluate(plain, {}, run_dir, simulator_for(plain))
    if ev.responses is None:
        raise SystemExit(f"the deck's own run failed ({run_dir}): {ev.reason}")
    wells = sorted(case.info.wells)
    summary = min(run_dir.glob("*.SMSPEC"))
    forecast = truth_forecast(read_curves(summary, wells), wells)
    doc = {"kind": FIELD_KIND, "seed": None, "case": str(case.source),
           "truth": "the deck's own fields (PUNQ-S3's truth)",
           "fields": [{"name": f.name, "keyword": f.keyword,
                       "space": "log10" if f.in_log else "value"} for f in case.fields],
           "layout": {"fields": list(layout.fields), "scalars": [], "n_active": grid.n_active},
           "truth_table": str(out / TRUTH_TABLE), "truth_run": str(run_dir),
           "truth_grdecl": str(write_truth_grdecl(case, grid, out)),
           "summary": str(summary), "schedule_end_days": float(case.info.end_days),
           "FOPT": next(r["value"] for r in forecast if r["quantity"] == "FOPT"),
           "forecast": forecast}
    doc_path.write_text(json.dumps(doc, indent=2) + "\n")
    return doc_path


def toml_value(text: str):
    """A ``--set`` value as TOML reads it (``1500``, ``[4, 2, 1]``, ``"distance"``), a bare
    word as a string (``distance``)."""
    try:
        return tomlkit.parse(f"v = {text}")["v"]
    except tomlkit.exceptions.ParseError:
        return text


def case_with(case_path: Path, sets: list[str], out: Path, truth_json: Path) -> Path:
    """A copy of the case file in ``out`` with ``[ensemble]`` keys changed
    (``ensemble_calibration.case_copy``) and the truth's ``hidden_truth.json`` beside it, so
    that the ensemble's report draws the truth in its fans and maps (it looks beside the case
    file, as for ``hmflow hide``'s cases)."""
    keys = {k.strip(): toml_value(v.strip()) for k, _, v in (item.partition("=") for item in sets)}
    case = case_copy(case_path, keys, out)
    beside = case.parent / TRUTH_JSON
    if not beside.is_file() or beside.read_text() != truth_json.read_text():
        beside.write_text(truth_json.read_text())
    return case


def run(case: Path, store: Path, campaign: str, workers: int) -> float:
    started = time.time()
    subprocess.run([sys.executable, "-m", "hmflow.cli", "ensemble", "--case", str(case),
                    "--campaign", campaign, "--storage", str(store), "--workers", str(workers)],
                   check=True, timeout=6 * 3600)
    return time.time() - started


def layer_errors(store: ArtifactStore, campaign: str, truth_doc: dict, last: int,
                 dims: tuple[int, int, int], active: np.ndarray) -> list[dict]:
    """RMSE of the mean field and the members' mean sd, per field and layer, prior and
    posterior."""
    layout = Layout(tuple(truth_doc["layout"]["fields"]), (), truth_doc["layout"]["n_active"])
    truth = ensemble_matrix(pd.read_parquet(truth_doc["truth_table"]), layout)[0]
    layer = active // (dims[0] * dims[1]) + 1  # k of each active cell, 1-based
    rows = []
    for i, label in ((0, "prior"), (last, "posterior")):
        X = kept(ensemble_matrix(store.latest(campaign, ensemble_step(i)).read_parquet(
            ENSEMBLE_FILE), layout))
        for name in layout.fields:
            cols = layout.columns(name)
            for k in np.unique(layer):
                sel = np.flatnonzero(layer == k)
                x, t = X[:, cols][:, sel], truth[cols][sel]
                rows.append({"ensemble": label, "field": name, "layer": int(k),
                             "rmse": float(np.sqrt(np.mean((x.mean(axis=0) - t) ** 2))),
                             "sd": float(x.std(axis=0, ddof=1).mean()),
                             "members": int(X.shape[0])})
    return rows


def cost(store: ArtifactStore, campaign: str, rounds: int, workers: int) -> dict:
    """Wall time of the members' runs against the simulator time per worker, per round and in
    all (a round's wall time: from its first run's start to its last run's end)."""
    out, total_wall, total_sim = [], 0.0, 0.0
    for i in range(rounds):
        records = EvaluationJournal(store, campaign, member_journal(i)).rows()
        if not records:
            continue
        starts = [r["finished_at"] - r["wall_time_s"] for r in records]
        wall = max(r["finished_at"] for r in records) - min(starts)
        sim = sum(r["sim_time_s"] for r in records)
        total_wall += wall
        total_sim += sim
        out.append({"round": i, "runs": len(records), "wall_s": wall,
                    "sim_s_per_worker": sim / workers,
                    "overhead": wall / (sim / workers) - 1.0,
                    "sim_s_per_run": sim / len(records)})
    return {"rounds": out, "wall_s": total_wall, "sim_s_per_worker": total_sim / workers,
            "overhead": total_wall / (total_sim / workers) - 1.0 if total_sim else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--case", type=Path, default=DEFAULT_CASE)
    ap.add_argument("--campaign", default="punq-es")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change a key of the case's [ensemble] section (TOML value)")
    ap.add_argument("--evaluate-only", action="store_true",
                    help="judge the stored run; simulate nothing")
    args = ap.parse_args()
    out = args.out.resolve()
    store_dir = out / "store"
    truth_json = write_deck_truth(args.case.resolve(), out / "truth")
    case = case_with(args.case.resolve(), args.set, out / f"case-{args.campaign}", truth_json)
    seconds = None if args.evaluate_only else run(case, store_dir, args.campaign, args.workers)
    store = ArtifactStore(store_dir)
    settings = store.settings(args.campaign)
    last = len(EnsembleSpec.model_validate(settings["ensemble"]).alphas)
    revealed = reveal_field_truth(truth_json, store_dir, args.campaign)
    truth_doc = json.loads(truth_json.read_text())
    prior = store.latest(args.campaign, ensemble_step(0))
    meta = prior.read_json(ENSEMBLE_DOC)
    active = prior.read_parquet("grid.parquet")["active"].to_numpy()
    layers = layer_errors(store, args.campaign, truth_doc, last, tuple(meta["dims"]), active)
    summary = store.latest(args.campaign, FORECAST_STEP).read_json("summary.json")
    spent = cost(store, args.campaign, last + 1, args.workers)
    result = {"campaign": args.campaign, "case": str(case), "ensemble": settings["ensemble"],
              "command_seconds": seconds, "fopt_inside": revealed.fopt_inside,
              "checks": [{**c.__dict__, "inside": c.inside, "width": c.width}
                         for c in revealed.checks],
              "errors": [{**e.__dict__, "collapsed": e.collapsed,
                         "prior_holds_truth": e.prior_holds_truth} for e in revealed.errors], "layers": layers,
              "rounds": summary["iterations"], "updates": summary["updates"], "cost": spent}
    (out / f"{args.campaign}.json").write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"## {args.campaign}: {settings['ensemble']}\n")
    print("| ensemble | quantity | truth | P90 | P50 | P10 | inside | width |")
    print("|---|---|---|---|---|---|---|---|")
    for c in revealed.checks:
        print(f"| {c.ensemble} | {c.well} {c.quantity} | {c.truth:.4g} | {c.P90:.4g} | "
              f"{c.P50:.4g} | {c.P10:.4g} | {'yes' if c.inside else 'NO'} | {c.width:.3f} |")
    print("\n| field | space | RMSE prior mean | RMSE posterior mean | spread prior | "
          "spread posterior | posterior RMSE/spread |\n|---|---|---|---|---|---|---|")
    for e in revealed.errors:
        print(f"| {e.field} | {e.space} | {e.rmse_prior:.4f} | {e.rmse_posterior:.4f} | "
              f"{e.sd_prior:.4f} | {e.sd_posterior:.4f} | {e.error_to_spread[1]:.2f} |")
    print("\n| field | layer | RMSE prior | RMSE posterior | sd prior | sd posterior |")
    print("|---|---|---|---|---|---|")
    by = {(r["ensemble"], r["field"], r["layer"]): r for r in layers}
    for (e, f, k), r in by.items():
        if e == "prior":
            p = by[("posterior", f, k)]
            print(f"| {f} | {k} | {r['rmse']:.4f} | {p['rmse']:.4f} | {r['sd']:.4f} | "
                  f"{p['sd']:.4f} |")
    print("\n| round | planned | ran | failed | misfit median | misfit mean |")
    print("|---|---|---|---|---|---|")
    for r in summary["iterations"]:
        print(f"| {r['iteration']} | {r['planned']} | {r['ran']} | {r['failed']} | "
              f"{r['misfit_median']:.3g} | {r['misfit_mean']:.3g} |")
    print(f"\ncost: members' runs {spent['wall_s']:.0f} s wall against "
          f"{spent['sim_s_per_worker']:.0f} s of simulator time per worker "
          f"(overhead {spent['overhead']:+.1%}); updates "
          f"{[u.get('update_seconds') for u in summary['updates']]} s; the command "
          f"{seconds if seconds is None else round(seconds)} s")


if __name__ == "__main__":
    main()
