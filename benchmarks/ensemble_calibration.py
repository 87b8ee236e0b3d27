"""Is the ensemble's forecast calibrated? Hidden truths drawn from a case's prior, an ensemble
run on each, and the share of truths inside the posterior's P10-P90 (issue 41).

    python benchmarks/ensemble_calibration.py --case CASE --out DIR --truths 1 2 ... \
        [--variant none] [--variant distance:radius=1500] [--variant adaptive] \
        [--set size=50] [--stated-noise] [--workers 2] [--max-minutes 120]

For each truth seed s: ``hmflow hide --kind field --case CASE --out DIR/truth-s --seed s``
(a truth drawn from CASE's own prior, never one of the members, simulated over the whole
schedule, PUNQ-S3's noise on its history); then, for each variant, the ensemble run
``DIR/store`` campaign ``t<s>-<variant>`` on that hidden case with the variant's ``[ensemble]``
keys (``--set`` applies to every variant; a variant is ``localisation[:key=value,...]``),
and ``hmflow reveal``'s judgement: for FOPT, FWPT, FGPT and each well's WOPT at the
schedule's end, is the truth inside the prior's and the posterior's P10-P90, and how far the
mean fields are from the truth's.

With ``--stated-noise`` every campaign (``t<s>-<variant>-sigma``) fits a copy of the hidden
history with the noise that made it in its ``sigma`` column (drawn again from the truth's noise
stream and checked against the stored history), instead of the noise estimated from the data:
what the smoother's calibration is when the noise is right.

Everything resumes: a truth already drawn is kept, a campaign already run is judged from the
store, a campaign cut short is resumed by its own journal. ``--max-minutes`` stops starting new
campaigns after that long (run it again for the next slice). Rows go to ``DIR/calibration.csv``
(one per truth, variant, ensemble and quantity) and ``DIR/fields.csv``; the summary (share
inside per variant and quantity, with its count) is printed as Markdown. Nothing is asserted.
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

from hmcore.cases import load_case  # noqa: E402
from hmcore.scenarios.field_truth import (  # noqa: E402
    TRUTH_JSON,
    hide_field_truth,
    reveal_field_truth,
    truth_streams,
)
from hmcore.scenarios.hidden import noisy_history  # noqa: E402
from hmflow.cli.flowrun import start_api  # noqa: E402
from storage import ArtifactStore  # noqa: E402
from storage.ensemble import FORECAST_STEP  # noqa: E402


def variant_keys(variant: str) -> tuple[str, dict]:
    """'distance:radius=1500' -> ('distance-r1500', {'localisation': 'distance', 'radius':
    1500.0})."""
    kind, _, rest = variant.partition(":")
    keys: dict = {"localisation": kind}
    label = kind
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        keys[k.strip()] = tomlkit.parse(f"v = {v.strip()}")["v"]
        label += f"-{k.strip()[0]}{v.strip()}"
    return label, keys


def stated_history(hidden_dir: Path, dest: Path) -> Path:
    """``dest/observed.csv``: the hidden history of ``hidden_dir`` with the sigma that made it.

    The noise is drawn again as :func:`hmcore.scenarios.field_truth.hide_field_truth` drew it
    (the truth's noise stream, ``noisy_history`` on ``truth_responses.csv``); the values must
    equal the stored ``observed.csv`` (to its 6 digits), or the history is not the one hidden."""
    doc = json.loads((hidden_dir / TRUTH_JSON).read_text())
    stored = pd.read_csv(hidden_dir / "observed.csv")
    truth = pd.read_csv(hidden_dir / "truth_responses.csv")
    rng = np.random.default_rng(truth_streams(doc["seed_stream"]["entropy"], doc["seed"])[2])
    drawn = noisy_history(truth[truth.well.isin(stored.well.unique())], rng)
    drawn = drawn[drawn.days <= doc["history_end_days"] + 1e-9].reset_index(drop=True)
    key = ["well", "days", "quantity"]
    both = stored.merge(drawn[key + ["value", "sigma"]], on=key, suffixes=("", "_drawn"))
    if len(both) != len(stored) or not np.allclose(both.value, both.value_drawn, rtol=1e-5,
                                                   atol=1e-9):
        raise ValueError(f"{hidden_dir}: the noise drawn again does not give the stored history")
    dest.mkdir(parents=True, exist_ok=True)
    out = dest / "observed.csv"
    both.drop(columns=["value_drawn"]).to_csv(out, index=False, float_format="%.6g")
    return out


def case_copy(hidden_case: Path, keys: dict, dest: Path, observed: Path | None = None) -> Path:
    """A case file with its ``[ensemble]`` keys set, its deck and history by absolute path (a
    copy in ``dest``, rewritten only when it changes); ``observed`` replaces the history."""
    doc = tomlkit.parse(hidden_case.read_text())
    for section in ("deck", "observed"):
        doc["case"][section] = str((hidden_case.parent / doc["case"][section]).resolve())
    if observed is not None:
        doc["case"]["observed"] = str(observed.resolve())
    ensemble = doc.setdefault("ensemble", tomlkit.table())
    for k, v in keys.items():
        ensemble[k] = v
    if "localisation" in keys and keys["localisation"] != "distance" and "radius" in ensemble:
        del ensemble["radius"]
    dest.mkdir(parents=True, exist_ok=True)
    out = dest / "case.toml"
    text = tomlkit.dumps(doc)
    if not out.is_file() or out.read_text() != text:
        out.write_text(text)
    return out


def judged_rows(truth: int, label: str, hidden: Path, store: Path, campaign: str
                ) -> tuple[list[dict], list[dict]]:
    revealed = reveal_field_truth(hidden, store, campaign)
    checks = [{"truth": truth, "variant": label, "ensemble": c.ensemble, "well": c.well,
               "quantity": c.quantity, "value": c.truth, "P90": c.P90, "P50": c.P50,
               "P10": c.P10, "members": c.members, "inside": c.inside, "width": c.width}
              for c in revealed.checks]
    errors = [{"truth": truth, "variant": label, "field": e.field, "space": e.space,
               "rmse_prior": e.rmse_prior, "rmse_posterior": e.rmse_posterior, "sd_prior": e.sd_prior,
               "sd_posterior": e.sd_posterior, "collapsed": e.collapsed,
               "prior_holds_truth": e.prior_holds_truth}
              for e in revealed.errors]
    return checks, errors


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--truths", type=int, nargs="+", required=True)
    ap.add_argument("--variant", action="append", default=[],
                    help="localisation[:key=value,...]; default: none and adaptive")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an [ensemble] key for every variant (e.g. size=50)")
    ap.add_argument("--stated-noise", action="store_true",
                    help="fit the history with the sigma that made it (campaigns '...-sigma')")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-minutes", type=float, default=None)
    args = ap.parse_args()

    start_api()  # hmflow's: a SIGTERM to this group stops the run; logs drained at exit
    from flows.ensemble import ensemble_flow  # Prefect reads its API's URL on import

    started = time.time()
    out = args.out.resolve()
    store = out / "store"
    common = {k.strip(): tomlkit.parse(f"v = {v.strip()}")["v"]
              for k, _, v in (item.partition("=") for item in args.set)}
    variants = [variant_keys(v) for v in (args.variant or ["none", "adaptive"])]
    if args.stated_noise:
        variants = [(f"{label}-sigma", keys) for label, keys in variants]
    base = load_case(args.case)
    checks, errors, skipped = [], [], []
    for s in args.truths:
        hidden_dir = out / f"truth-{s}"
        hidden = hidden_dir / TRUTH_JSON
        for label, keys in variants:
            campaign = f"t{s}-{label}"
            done = ArtifactStore(store).latest(campaign, FORECAST_STEP) is not None
            late = args.max_minutes is not None and time.time() - started > 60 * args.max_minutes
            if not done and late:
                skipped.append(campaign)
                continue
            if not hidden.is_file():
                print(f"truth {s}: drawn and run into {hidden_dir}", flush=True)
                hide_field_truth(base, hidden_dir, s)
            if not done:
                dest = out / "cases" / campaign
                observed = stated_history(hidden_dir, dest) if args.stated_noise else None
                case = case_copy(hidden_dir / "case.toml", {**common, **keys}, dest, observed)
                print(f"{campaign}: ensemble run ({time.time() - started:.0f} s in)", flush=True)
                result = ensemble_flow(case=str(case), workers=args.workers,
                                       storage=str(store), campaign=campaign)
                if not isinstance(result, dict):
                    print(f"{campaign}: did not finish: {result}", flush=True)
                    continue
            c, e = judged_rows(s, label, hidden, store, campaign)
            checks += c
            errors += e
    if not checks:
        print("nothing judged yet")
        return
    table = pd.DataFrame(checks)
    table.to_csv(out / "calibration.csv", index=False)
    pd.DataFrame(errors).to_csv(out / "fields.csv", index=False)
    print(summary(table, pd.DataFrame(errors)))
    if skipped:
        print(f"\nnot started (--max-minutes): {', '.join(skipped)}; run again to go on")


def summary(table: pd.DataFrame, errors: pd.DataFrame) -> str:
    """Markdown: per variant and quantity, the truths inside the prior's and the posterior's
    P10-P90 (count and share) and the median relative band width; per variant and field, the
    median RMSE of the mean field to the truth, prior and posterior, how often the
    posterior's is the smaller, the median RMSE over the members' spread (about 1 when the
    truth is like a member) and how often the posterior collapsed
    (:attr:`~hmcore.fields.spread.FieldSpread.collapsed`)."""
    lines = ["| variant | quantity | truths | inside prior | inside posterior | "
             "median width prior | median width posterior |", "|---|---|---|---|---|---|---|"]
    table = table.assign(name=table.well.where(table.well != "FIELD", "") + " " + table.quantity)
    for (variant, name), g in table.groupby(["variant", "name"], sort=True):
        pr, po = g[g.ensemble == "prior"], g[g.ensemble == "posterior"]
        lines.append(f"| {variant} | {name.strip()} | {len(po)} | {int(pr.inside.sum())} "
                     f"({pr.inside.mean():.0%}) | {int(po.inside.sum())} ({po.inside.mean():.0%})"
                     f" | {pr.width.median():.3f} | {po.width.median():.3f} |")
    lines += ["", "| variant | field | truths | median RMSE prior | median RMSE posterior | "
              "posterior closer | median RMSE/spread prior | posterior | collapsed |",
              "|---|---|---|---|---|---|---|---|---|"]
    for (variant, field), g in errors.groupby(["variant", "field"], sort=True):
        closer = int((g.rmse_posterior < g.rmse_prior).sum())
        lines.append(f"| {variant} | {field} | {len(g)} | {g.rmse_prior.median():.4f} | "
                     f"{g.rmse_posterior.median():.4f} | {closer} of {len(g)} | "
                     f"{(g.rmse_prior / g.sd_prior).median():.2f} | "
                     f"{(g.rmse_posterior / g.sd_posterior).median():.2f} | "
                     f"{int(g.collapsed.sum())} of {len(g)} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
