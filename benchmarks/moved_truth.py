"""The default method against CMA-ES on PUNQ-S3 histories made from moved truths, without a
sigma column, with noise of a law the noise estimate was not tuned on (issue 47's benchmark).

    python benchmarks/moved_truth.py --out bench-moved [--truths 1 2 3 4 5]
        [--generators white-laplace ar1-laplace] [--levels 0.5 1 2] [--methods lm cmaes]
        [--budget 100] [--workers 2] [--max-campaigns N] [--results FILE] [--git-commit]
    python benchmarks/moved_truth.py --out bench-moved --table      # the tables, no run

* **Truths**: the five reference globals drawn uniformly in the paper's box until no physics
  check fires (``make_bench_cases.draw_valid_truth``, ``default_rng([seed, 17])``), one OPM
  Flow run of PUNQ-S3 each (``OUT/truth-<seed>/``; the deck is read in place from
  ``../shared/punqs3/``, never copied).
* **Noise** (``noisy``), per well along its rows: BHP ``level x 2`` bar on every row, GOR and
  water cut ``level x 3 %`` of the true value on flowing rows (issue 47's history), the oil
  rate exact (the rate control); innovations of unit variance from the Laplace law (double
  exponential: not the Gaussian, Student-t or uniform laws of ``noise_estimates.py``, which
  the estimate was tuned on), white (``white-laplace``) or AR(1) along the rows with rho 0.6
  (``ar1-laplace``), ``default_rng([seed, level * 10, generator index, 4711])``. No ``sigma``
  column. The whole 8-year record is fitted (``history_end_days = 2936``, as
  ``make_bench_cases.py``).
* **Campaigns**: ``hmflow run`` (the case's default objective, the likelihood) with each method,
  seed 0, ``--budget`` calls, ``--workers`` workers, in the store ``OUT/store``; a campaign
  already complete is read as it is, a stopped one resumes (the same command again).
  ``--max-campaigns N`` stops after N campaigns were run by this invocation (a slice).
* **Figures**, per campaign, from its journal and its results (the likelihood of every call and
  of the truth under the noise the campaign ended with): the first call whose best valid E so
  far is within 1.1x the truth's E, the same for the likelihood (the objective it minimises),
  and the longest run of consecutive calls (failed ones included) whose own E, or likelihood,
  is above 5x the campaign's first call's. Written after every campaign to ``--results``
  (default ``benchmarks/results/moved-truth/results.json``), committed when ``--git-commit``
  (``git commit -- FILE``: that file only).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from make_bench_cases import draw_valid_truth  # noqa: E402

from hmcore.calibration.registry import method_version  # noqa: E402
from hmcore.eclipse.deck_info import DeckInfo  # noqa: E402
from hmcore.model.parameters import ParameterSpace  # noqa: E402
from hmcore.model.run_deck import prepare_run_deck  # noqa: E402
from hmcore.simulation.simulator import OpmFlow  # noqa: E402
from hmcore.simulation.responses import read_responses  # noqa: E402

DECK = REPO.parent / "shared/punqs3/PUNQS3.DATA"
RECORD_END = 2936.0
GENERATORS = ("white-laplace", "ar1-laplace")
AR1_RHO = 0.6
BHP_BAR, REL = 2.0, 0.03
RESULTS = REPO / "benchmarks/results/moved-truth/results.json"


# ----------------------------------------------------------------------------- histories
def innovations(rng: np.random.Generator, n: int, generator: str) -> np.ndarray:
    """Unit-variance Laplace innovations, white or AR(1) along the rows."""
    e = rng.laplace(0.0, 1.0 / math.sqrt(2.0), n)
    if generator == "white-laplace":
        return e
    out = np.empty(n)
    for k in range(n):
        out[k] = e[k] if k == 0 else AR1_RHO * out[k - 1] + math.sqrt(1 - AR1_RHO ** 2) * e[k]
    return out


def noisy(truth: pd.DataFrame, rng: np.random.Generator, generator: str, level: float
          ) -> pd.DataFrame:
    """Observed rows (well, days, quantity, value, flowing) from noise-free responses: see the
    module docstring. No sigma column."""
    wide = truth[(truth.days >= 0.5) & (truth.days <= RECORD_END + 1e-9)].pivot_table(
        index=["well", "days"], columns="quantity", values="value")
    rows = []
    for well in sorted(wide.index.get_level_values("well").unique()):
        t = wide.loc[well]
        days = t.index.to_numpy(float)
        wopr = t["WOPR"].to_numpy(float)
        flowing = wopr > 0.0
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WOPR",
                                  "value": wopr, "flowing": flowing.astype(int)}))
        bhp = t["WBHP"].to_numpy(float) + level * BHP_BAR * innovations(rng, days.size, generator)
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WBHP",
                                  "value": bhp, "flowing": flowing.astype(int)}))
        for q, top in (("WGOR", np.inf), ("WWCT", 1.0)):
            v = t[q].to_numpy(float)[flowing]
            noisy_v = np.clip(v * (1.0 + level * REL * innovations(rng, v.size, generator)),
                              0.0, top)
            rows.append(pd.DataFrame({"well": well, "days": days[flowing], "quantity": q,
                                      "value": noisy_v, "flowing": 1}))
    return pd.concat(rows, ignore_index=True)


def truth_run(out: Path, seed: int) -> tuple[dict[str, float], pd.DataFrame]:
    """The truth of ``seed`` and its noise-free responses (one OPM run, kept in OUT; the
    table is written last, atomically: a run killed before it is run again from scratch)."""
    folder = out / f"truth-{seed}"
    table = folder / "truth_responses.csv"
    truth = draw_valid_truth(seed, DECK.resolve())
    if not table.is_file():
        shutil.rmtree(folder / "run", ignore_errors=True)  # a killed run's leftovers
        info = DeckInfo.inspect(DECK.resolve())
        deck = prepare_run_deck(DECK.resolve(), truth, ParameterSpace.reference(),
                                folder / "run", info)
        result = OpmFlow().run(deck, folder / "run")
        partial = table.with_suffix(".part")
        read_responses(result.summary_path, sorted(info.wells)).to_csv(partial, index=False)
        os.replace(partial, table)
    return truth, pd.read_csv(table)


def make_case(out: Path, seed: int, generator: str, level: float) -> Path:
    """``OUT/punq-mt-<seed>-<generator>-x<level>/case.toml`` (written once)."""
    name = f"punq-mt-{seed}-{generator}-x{level:g}"
    folder = out / name
    case = folder / "case.toml"
    if case.is_file():
        return case
    truth, responses = truth_run(out, seed)
    rng = np.random.default_rng([seed, int(round(level * 10)), GENERATORS.index(generator),
                                 4711])
    folder.mkdir(parents=True, exist_ok=True)
    noisy(responses, rng, generator, level).to_csv(folder / "observed.csv", index=False,
                                                   float_format="%.6g")
    (folder / "hidden_effect.json").write_text(json.dumps(
        {"effect": None, "truth": truth,
         "noise": {"generator": generator, "level": level, "bhp_bar": level * BHP_BAR,
                   "gor_wct_relative": level * REL,
                   "ar1_rho": AR1_RHO if generator == "ar1-laplace" else 0.0}}, indent=2))
    case.write_text(f'[case]\nname = "{name}"\ndeck = "{DECK.resolve()}"\n'
                    f'observed = "observed.csv"\nhistory_end_days = {RECORD_END:g}\n')
    return case


# ----------------------------------------------------------------------------- figures
def first_within(values: list[float], floor: float, factor: float = 1.1) -> float:
    """The first call (1-based) whose best value so far is within ``factor`` x ``floor``."""
    best = math.inf
    for k, v in enumerate(values, start=1):
        if v is not None and math.isfinite(v):
            best = min(best, v)
        if best <= factor * floor:
            return float(k)
    return math.inf


def longest_above(values: list[float], factor: float = 5.0) -> int:
    """The longest run of consecutive calls whose own value is above ``factor`` x the first
    call's (a call without a value counts as above)."""
    start = values[0] if values else None
    if start is None or not math.isfinite(start):
        return len(values)
    run = longest = 0
    for v in values:
        run = run + 1 if (v is None or not math.isfinite(v) or v > factor * start) else 0
        longest = max(longest, run)
    return longest


def figures(store: Path, campaign: str, budget: int) -> dict | None:
    """One campaign's figures from its stored results (None while it has none)."""
    results = sorted((store / campaign / "results").glob("v*/records.json"))
    if not results:
        return None
    doc = json.loads(results[-1].read_text())
    records = sorted((r for r in doc["records"] if r["index"] < budget),
                     key=lambda r: r["index"])
    if len(records) < budget:
        return None
    refs = doc.get("references") or {}
    floor_e = (refs.get("floor") or {}).get("E")
    floor_l = (refs.get("floor") or {}).get("likelihood")

    def valid(r: dict, key: str):
        v = r.get(key)
        return v if r["status"] == "COMPLETE" and v is not None else None

    e_valid = [valid(r, "E") for r in records]
    l_valid = [valid(r, "likelihood") for r in records]
    e_own = [r.get("E") for r in records]
    l_own = [r.get("likelihood") for r in records]
    noise = doc.get("noise") or {}
    best_e = min((v for v in e_valid if v is not None), default=math.nan)
    best_l = min((v for v in l_valid if v is not None), default=math.nan)
    return {"objective": doc.get("objective"), "floor_E": floor_e, "floor_likelihood": floor_l,
            "calls_to_1.1x_E": first_within(e_valid, floor_e) if floor_e else math.inf,
            "calls_to_1.1x_likelihood": (first_within(l_valid, floor_l) if floor_l
                                         else math.inf),
            "longest_above_5x_start_E": longest_above(e_own),
            "longest_above_5x_start_likelihood": longest_above(l_own),
            "best_E_over_floor": best_e / floor_e if floor_e else math.nan,
            "best_likelihood_over_floor": best_l / floor_l if floor_l else math.nan,
            "first_E_over_floor": (e_own[0] / floor_e if floor_e and e_own[0] else math.nan),
            "noise_refinements": noise.get("refinement", 0),
            "penalised": sum(r["status"] == "INVALID" for r in records),
            "failed": sum(r["status"] == "FAIL" for r in records)}


def save(path: Path, results: dict, git_commit: bool) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(results, indent=1, sort_keys=True, default=str))
    os.replace(tmp, path)
    if git_commit:
        subprocess.run(["git", "add", str(path)], cwd=REPO, check=True)
        subprocess.run(["git", "commit", "-q", "-m", f"moved-truth benchmark: {len(results)} "
                        "campaigns in " + path.name, "--", str(path)], cwd=REPO, check=False)


def method_tag(method: str) -> str:
    """The method as campaigns and the tables name it: with its version when it has had
    several (``lm-v6``; the results of ``lm`` 4, from before the tag, say ``lm-v4``)."""
    version = method_version(method)
    return f"{method}-v{version}" if version > 1 else method


def table(results: dict) -> str:
    """Per method, generator and level: medians over the truths (never: more than half
    missed), and the worst longest run above 5x."""
    df = pd.DataFrame(results.values())
    if df.empty:
        return "no results yet\n"
    lines = ["| method | generator | level | truths | calls to 1.1x E (median) | calls to 1.1x "
             "likelihood (median) | longest run above 5x start, E (worst) | same, likelihood "
             "(worst) | best E / truth's (median) |", "|---|---|---|---|---|---|---|---|---|"]

    def med(s: pd.Series) -> str:
        v = float(np.median(s.astype(float)))
        return "never" if not math.isfinite(v) else f"{v:.0f}"

    for (m, g, lv), part in df.groupby(["method", "generator", "level"], sort=True):
        lines.append(f"| {m} | {g} | x{lv:g} | {len(part)} | {med(part['calls_to_1.1x_E'])} | "
                     f"{med(part['calls_to_1.1x_likelihood'])} | "
                     f"{int(part['longest_above_5x_start_E'].max())} | "
                     f"{int(part['longest_above_5x_start_likelihood'].max())} | "
                     f"{float(np.median(part['best_E_over_floor'])):.3f} |")
    for m, part in df.groupby("method"):
        lines.append(f"| {m} | all | all | {len(part)} | {med(part['calls_to_1.1x_E'])} | "
                     f"{med(part['calls_to_1.1x_likelihood'])} | "
                     f"{int(part['longest_above_5x_start_E'].max())} | "
                     f"{int(part['longest_above_5x_start_likelihood'].max())} | "
                     f"{float(np.median(part['best_E_over_floor'])):.3f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--truths", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--generators", nargs="+", default=list(GENERATORS), choices=GENERATORS)
    ap.add_argument("--levels", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    ap.add_argument("--methods", nargs="+", default=["lm", "cmaes"])
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-campaigns", type=int, default=None)
    ap.add_argument("--results", type=Path, default=RESULTS)
    ap.add_argument("--git-commit", action="store_true")
    ap.add_argument("--table", action="store_true", help="print the tables of --results only")
    args = ap.parse_args()
    results = json.loads(args.results.read_text()) if args.results.is_file() else {}
    if args.table:
        print(table(results))
        return
    out = args.out.resolve()
    store = out / "store"
    ran = 0
    for seed in args.truths:
        for generator in args.generators:
            for level in args.levels:
                case = make_case(out, seed, generator, level)
                for method in args.methods:
                    tag = method_tag(method)
                    name = f"{case.parent.name}-{tag}-b{args.budget}-w{args.workers}"
                    found = figures(store, name, args.budget)
                    if found is None:
                        if args.max_campaigns is not None and ran >= args.max_campaigns:
                            print(f"stopped after {ran} campaigns (--max-campaigns)")
                            print(table(results))
                            return
                        subprocess.run([str(Path(sys.executable).parent / "hmflow"), "run",
                                        "--case", str(case), "--agent", method, "--budget",
                                        str(args.budget), "--workers", str(args.workers),
                                        "--seed", "0", "--forecast-draws", "0",
                                        "--campaign", name, "--storage",
                                        str(store)], check=True)
                        ran += 1
                        found = figures(store, name, args.budget)
                    if found is None:
                        raise RuntimeError(f"campaign {name} left no results in {store}")
                    results[name] = {"truth": seed, "generator": generator, "level": level,
                                     "method": tag, "budget": args.budget,
                                     "workers": args.workers, **found}
                    save(args.results, results, args.git_commit)
                    print(f"{name}: {json.dumps(found, default=str)}")
    print(table(results))


if __name__ == "__main__":
    main()
