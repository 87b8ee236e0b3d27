"""Noise estimated from histories without sigma, against the noise that made them.

    python benchmarks/noise_estimates.py [--seeds 5] [--json out.json]
    python benchmarks/noise_estimates.py --from-json out.json     # the tables again

Histories with known noise are made by hmflow's own generators from noise-free truths that need
no simulation:

* PUNQ-S3: the OPM truth run of ``PUNQS3.DATA`` (``reference_opm2026.4_PUNQS3_truth_summary.csv``
  in the shared data) over the 8-year record (to day 2936, as PUNQ-S3's observed history: the
  yearly two-week shut-ins, a water cut of ~1e-5 to 1e-3) and over the whole schedule (to day
  6025: water breakthrough in four wells);
* the built-in synthetic case (its ``truth_responses.csv``; monthly steps, a yearly shut-in).

Noise is added through :func:`hmcore.scenarios.synthetic.noisy_series` (directly or by
:func:`hmcore.scenarios.hidden.noisy_history`) with a :class:`hmcore.scoring.noise.NoiseModel`
scaled to each level (x0.5, x1, x2 of PUNQ-S3's table: BHP 3 bar flowing / 1 bar shut in, GOR
10 % / 25 % of the value before / after gas breakthrough, WCT 0.02 / 0.05 before / after water
breakthrough) and one of these innovation generators (:class:`Innovations` stands in for the
random generator):

* ``ar1-normal``: Gaussian AR(1), rho 0.7 (the model the estimator assumes);
* ``white-t3``: Student-t with 3 degrees of freedom scaled to unit variance, no correlation;
* ``uniform-gauss45d``: uniform innovations correlated in time with a Gaussian shape,
  ``exp(-(dt / 45 days)^2 / 2)`` (not AR(1), and in days rather than rows);

and ``relative-t3`` (a new user's history without sigma): BHP white Student-t of 2 bar at level
x1, GOR and water cut Student-t of 3 % of the true value (so a water cut of 1e-5 has a noise of
3e-7), made here.

Each history loses its ``sigma`` column and goes through
:meth:`hmcore.scoring.observations.ObservationSet.from_observed` (fitted period: the first
75 % of the record, as a case without ``history_end_days``), then through ``refine`` on the
residuals against the noise-free truth. Per quantity and segment the tables give the median
over fitted rows of ``estimated sigma / true sigma`` (median over seeds and the worst seed)
and a verdict (see :func:`summarise`). Rows of the rate control (WOPR) carry no noise and are
left out.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hmcore.model.case import default_history_end
from hmcore.scenarios.hidden import noisy_history
from hmcore.scenarios.synthetic import noisy_series
from hmcore.scoring.noise import PUNQ_NOISE, NoiseModel
from hmcore.scoring.observations import ObservationSet

PUNQ_TRUTH = (Path(__file__).resolve().parents[2] / "shared" / "punqs3"
              / "reference_opm2026.4_PUNQS3_truth_summary.csv")
QUANTITIES = ("WOPR", "WBHP", "WGOR", "WWCT")
LEVELS = (0.5, 1.0, 2.0)
FACTOR = 1.5
"""An estimate within this factor of the true sigma counts as right."""


# ============================================================================ noise-free truths
def punq_truth(record_end: float) -> pd.DataFrame:
    """PUNQ-S3's OPM truth run, long table (well, days, quantity, value), days in (0.5, end]."""
    wide = pd.read_csv(PUNQ_TRUTH)
    rows = []
    for col in wide.columns:
        q, _, well = col.partition(":")
        if q in QUANTITIES and well:
            rows.append(pd.DataFrame({"well": well, "days": wide.DAYS.round(2), "quantity": q,
                                      "value": wide[col].to_numpy(float) + 0.0}))
    out = pd.concat(rows, ignore_index=True)
    out.loc[out.value.abs() < 1e-12, "value"] = 0.0
    return out[(out.days >= 0.5) & (out.days <= record_end + 1e-9)].reset_index(drop=True)


def synthetic_truth() -> pd.DataFrame:
    """The built-in synthetic case's noise-free responses (cached; simulated once if not)."""
    from hmcore.scenarios.synthetic import ensure_synthetic_case  # simulates on first use
    truth = pd.read_csv(ensure_synthetic_case(0).parent / "truth_responses.csv")
    return truth[truth.quantity.isin(QUANTITIES)].reset_index(drop=True)


# ============================================================================ innovation generators
class Innovations:
    """A stand-in for :class:`numpy.random.Generator` whose ``standard_normal(n)`` returns unit
    variance innovations of another law, so that hmflow's own noise path
    (:func:`hmcore.scenarios.synthetic.noisy_series`) draws noise the estimator does not assume.
    With ``corr_days`` > 0 the draws are correlated in time, ``exp(-(dt / corr_days)^2 / 2)``
    (a Gaussian shape in days, not AR(1) in rows), at the days given in ``days`` for each
    coming call, in order."""

    def __init__(self, rng: np.random.Generator, law: str, corr_days: float = 0.0):
        self.rng, self.law, self.corr_days = rng, law, corr_days
        self.days: list[np.ndarray] = []

    def _draw(self, n: int) -> np.ndarray:
        if self.law == "t3":
            return self.rng.standard_t(3, n) / math.sqrt(3.0)  # var of t_3 is 3
        if self.law == "uniform":
            return self.rng.uniform(-math.sqrt(3.0), math.sqrt(3.0), n)
        return self.rng.standard_normal(n)

    def standard_normal(self, n: int) -> np.ndarray:
        e = self._draw(n)
        if self.corr_days <= 0 or n == 0:
            return e
        d = self.days.pop(0)
        assert d.size == n
        corr = np.exp(-0.5 * ((d[:, None] - d[None, :]) / self.corr_days) ** 2)
        return np.linalg.cholesky(corr + 1e-9 * np.eye(n)) @ e


def scaled(noise: NoiseModel, level: float, rho: float) -> NoiseModel:
    return replace(noise, rho=rho, bhp_flowing=noise.bhp_flowing * level,
                   bhp_shut_in=noise.bhp_shut_in * level, gor_before=noise.gor_before * level,
                   gor_after=noise.gor_after * level, wct_before=noise.wct_before * level,
                   wct_after=noise.wct_after * level)


def _wide(truth: pd.DataFrame):
    wide = truth.pivot_table(index=["well", "days"], columns="quantity", values="value")
    for well in sorted(wide.index.get_level_values("well").unique()):
        t = wide.loc[well]
        yield well, t.index.to_numpy(float), t


def time_correlated_history(truth: pd.DataFrame, inn: Innovations, noise: NoiseModel
                            ) -> pd.DataFrame:
    """:func:`hmcore.scenarios.hidden.noisy_history`'s loop, telling ``inn`` the days of each
    series it draws (BHP at every row, GOR and WCT at the flowing ones)."""
    rows = []
    for well, days, t in _wide(truth):
        flowing = t["WOPR"].to_numpy() > 0
        inn.days += [days, days[flowing], days[flowing]]
        series, _, _ = noisy_series(days, t["WOPR"].to_numpy(), t["WBHP"].to_numpy(),
                                    t["WGOR"].to_numpy(), t["WWCT"].to_numpy(), inn, noise)
        rows += [pd.DataFrame({"well": well, "days": x.days, "quantity": x.quantity,
                               "value": x.value, "sigma": x.sigma,
                               "flowing": x.flowing.astype(int)}) for x in series]
    return pd.concat(rows, ignore_index=True)


def relative_history(truth: pd.DataFrame, rng: np.random.Generator, level: float
                     ) -> pd.DataFrame:
    """A new user's history: BHP white Student-t of 2 bar x level, GOR and water cut Student-t of
    3 % x level of the true value (clipped to >= 0, and the water cut to <= 1); WOPR the exact
    rate control; GOR and WCT while flowing."""
    inn = Innovations(rng, "t3")
    rows = []
    for well, days, t in _wide(truth):
        flowing = t["WOPR"].to_numpy() > 0
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WOPR",
                                  "value": t["WOPR"].to_numpy(), "sigma": np.nan,
                                  "flowing": flowing.astype(int)}))
        sig = np.full(days.size, 2.0 * level)
        rows.append(pd.DataFrame({"well": well, "days": days, "quantity": "WBHP",
                                  "value": t["WBHP"].to_numpy() + sig * inn.standard_normal(
                                      days.size), "sigma": sig,
                                  "flowing": flowing.astype(int)}))
        for q in ("WGOR", "WWCT"):
            v = t[q].to_numpy()[flowing]
            sig = 0.03 * level * np.abs(v)
            rows.append(pd.DataFrame({"well": well, "days": days[flowing], "quantity": q,
                                      "value": np.clip(v + sig * inn.standard_normal(v.size),
                                                       0.0, 1.0 if q == "WWCT" else None),
                                      "sigma": sig, "flowing": 1}))
    return pd.concat(rows, ignore_index=True)


@dataclass(frozen=True)
class Generator:
    name: str
    law: str
    rho: float = 0.0
    corr_days: float = 0.0


GENERATORS = (Generator("ar1-normal", "normal", rho=PUNQ_NOISE.rho),
              Generator("white-t3", "t3"),
              Generator("uniform-gauss45d", "uniform", corr_days=45.0),
              Generator("relative-t3", "t3"))


def history(truth: pd.DataFrame, gen: Generator, level: float, seed: int) -> pd.DataFrame:
    """A noisy history with the true sigma in ``sigma``."""
    rng = np.random.default_rng([seed, int(level * 100), len(gen.name)])
    if gen.name == "relative-t3":
        return relative_history(truth, rng, level)
    noise = scaled(PUNQ_NOISE, level, gen.rho)
    if gen.corr_days > 0:
        return time_correlated_history(truth, Innovations(rng, gen.law, gen.corr_days), noise)
    return noisy_history(truth, Innovations(rng, gen.law), noise)


# ============================================================================ comparison
def compare(obs_true: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Per quantity and segment: estimated against true sigma on the fitted rows, from the
    observed series (``ratio``) and re-estimated from the residuals against the noise-free
    truth (``refined``: :meth:`ObservationSet.refine`, as after a fit that found the truth)."""
    end = default_history_end(obs_true.days.min(), obs_true.days.max())
    blind = obs_true.drop(columns="sigma")
    est = ObservationSet.from_observed(blind, end)
    refined = est.refine(truth, blind)
    key = ["well", "quantity", "days"]
    rows = est.rows.assign(segment=list(est.segment), refined=refined.rows.sigma).merge(
        obs_true[key + ["sigma"]].rename(columns={"sigma": "true"}), on=key)
    rows = rows[(rows.period == "fit") & rows.in_vector & (rows.quantity != "WOPR")
                & (rows.true > 0)]
    flags = est.uninformative
    span = {(q, lv["well"], lv["segment"]): np.array(lv["sigma_range"]) / lv["sigma"]
            for q, entry in est.noise_report.items() for lv in entry.get("levels", [])
            if lv.get("uncertain") and "sigma_range" in lv and lv["sigma"] > 0}
    rows = rows.assign(ratio=rows.sigma / rows.true, refined=rows.refined / rows.true,
                       flagged=[(q, w) in flags for q, w in zip(rows.quantity, rows.well)])
    covered = [bool((k := span.get((q, w, g))) is not None and r * k[0] <= 1 <= r * k[1])
               for q, w, g, r in zip(rows.quantity, rows.well, rows.segment, rows.ratio)]
    rows = rows.assign(covered=covered)
    out = []
    for (q, seg), g in rows.groupby(["quantity", "segment"]):
        ok = g[~g.flagged]
        p10, p90 = np.percentile(g.ratio, [10, 90]) if len(g) else (np.nan, np.nan)
        out.append({"quantity": q, "segment": seg, "n": len(g), "flagged": int(g.flagged.sum()),
                    "ratio_all": float(g.ratio.median()) if len(g) else float("nan"),
                    "p10": float(p10), "p90": float(p90),
                    "default": int((ok.sigma_source == "default").sum()),
                    "covered": int(ok.covered.sum()),
                    "ratio": float(ok.ratio.median()) if len(ok) else float("nan"),
                    "refined": float(ok.refined.median()) if len(ok) else float("nan"),
                    "rho": est.rho.get(q, float("nan")),
                    "rho_refined": refined.rho.get(q, float("nan"))})
    return pd.DataFrame(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--json", type=Path, help="write every (history, segment) result here")
    ap.add_argument("--from-json", type=Path, help="only print the tables of a --json file")
    args = ap.parse_args()
    if args.from_json:
        res = pd.read_json(args.from_json, orient="records")
    else:
        truths = {"punqs3-8y": punq_truth(2936.0), "punqs3-16y": punq_truth(6025.0),
                  "synthetic": synthetic_truth()}
        results = []
        for tname, truth in truths.items():
            for gen in GENERATORS:
                for level in LEVELS:
                    for seed in range(args.seeds):
                        table = compare(history(truth, gen, level, seed), truth)
                        results.append(table.assign(truth=tname, generator=gen.name,
                                                    level=level, seed=seed))
        res = pd.concat(results, ignore_index=True)
        if args.json:
            args.json.write_text(res.to_json(orient="records", indent=1))
    summary = summarise(res)
    print(markdown(summary))
    print()
    counts = pd.crosstab(summary.truth, summary.verdict)
    print("| truth | " + " | ".join(counts.columns) + " |")
    print("|---|" + "---|" * len(counts.columns))
    for truth, row in counts.iterrows():
        print(f"| {truth} | " + " | ".join(str(int(x)) for x in row) + " |")


SEGMENTS = (("WBHP", "flowing"), ("WBHP", "shut_in"), ("WGOR", "before"), ("WGOR", "after"),
            ("WWCT", "before"), ("WWCT", "after"))


def markdown(summary: pd.DataFrame) -> str:
    """One line per truth, generator and level; per segment the median ratio over seeds, the
    worst seed's and the verdict; then the same from the residuals against the truth."""
    def cell(r: pd.Series, med: str, worst: str, verdict: str | None) -> str:
        if verdict == "flagged":
            return f"flagged {r[med + '_all']:.2f} ({r[worst + '_all']:.2f})" \
                if med + "_all" in r and np.isfinite(r[med + "_all"]) else "flagged"
        text = f"{r[med]:.2f} ({r[worst]:.2f})"
        return text if verdict is None or verdict == "ok" else f"{text} {verdict}"

    head = "| truth | generator | level | rho | " + " | ".join(
        f"{q[1:]} {s}" for q, s in SEGMENTS) + " |"
    rule = "|" + "---|" * (4 + len(SEGMENTS))
    out = []
    for title, med, worst, rho, with_verdict in (
            ("from the observed series (median over seeds (worst seed), verdict when not ok)",
             "median", "worst", "rho", True),
            ("re-estimated from the residuals against the truth (ObservationSet.refine)",
             "refined", "refined_worst", "rho_refined", False)):
        out += [f"**{title}**", "", head, rule]
        for (t, g, lv), part in summary.groupby(["truth", "generator", "level"], sort=False):
            cells = []
            for q, sg in SEGMENTS:
                row = part[(part.quantity == q) & (part.segment == sg)]
                if row.empty:
                    cells.append("-")
                    continue
                r = row.iloc[0]
                cells.append(cell(r, med, worst, r.verdict if with_verdict else (
                    "flagged" if r.verdict == "flagged" else None)))
            out.append(f"| {t} | {g} | x{lv:g} | {part[rho].median():.2f} | "
                       + " | ".join(cells) + " |")
        out.append("")
    out += [("**spread over rows: 10th-90th percentile of estimated / true sigma over the "
             "fitted rows (flagged ones too), lowest and highest over seeds**"), "",
            "| truth | generator | level | " + " | ".join(
                f"{q[1:]} {s}" for q, s in SEGMENTS if q != "WBHP") + " |",
            "|" + "---|" * (3 + len(SEGMENTS) - 2)]
    for (t, g, lv), part in summary.groupby(["truth", "generator", "level"], sort=False):
        cells = []
        for q, sg in SEGMENTS:
            if q == "WBHP":
                continue
            row = part[(part.quantity == q) & (part.segment == sg)]
            cells.append("-" if row.empty or not np.isfinite(row.iloc[0].p10) else
                         f"{row.iloc[0].p10:.2g}-{row.iloc[0].p90:.2g}")
        out.append(f"| {t} | {g} | x{lv:g} | " + " | ".join(cells) + " |")
    out.append("")
    return "\n".join(out)


def summarise(res: pd.DataFrame) -> pd.DataFrame:
    """Per truth, generator, level, quantity and segment: median and worst ratio over seeds
    and the verdict: ``ok`` (every seed within a factor 1.5), ``flagged`` (every row flagged
    uninformative), ``uncertain`` (not within 1.5, but the report flags the level uncertain
    and the true sigma lies in the range it gives, in every seed, for most rows), ``default`` (most rows took a
    level not estimated from their kind of segment: the default after breakthrough, the
    flowing level for shut-in BHP), ``OFF``."""
    def worst(r: pd.Series) -> float:
        r = r.dropna()
        return float(r.iloc[np.argmax(np.abs(np.log(r)))]) if len(r) else float("nan")

    g = res.groupby(["truth", "generator", "level", "quantity", "segment"], sort=False)
    extra = {"median_all": ("ratio_all", "median"), "worst_all": ("ratio_all", worst),
             "p10": ("p10", "min"), "p90": ("p90", "max")} if "p10" in res else {}
    out = g.agg(median=("ratio", "median"), worst=("ratio", worst), n=("n", "median"), **extra,
                flagged=("flagged", "median"), default=("default", "median"),
                covered=("covered", "min"),
                rho=("rho", "median"), refined=("refined", "median"),
                refined_worst=("refined", worst), rho_refined=("rho_refined", "median")
                ).reset_index()
    verdict = np.where(out.worst.between(1 / FACTOR, FACTOR), "ok", "OFF")
    verdict = np.where((verdict == "OFF") & (out.covered > (out.n - out.flagged) / 2),
                       "uncertain", verdict)
    verdict = np.where(out.default > (out.n - out.flagged) / 2, "default", verdict)
    out["verdict"] = np.where(out.flagged >= out.n, "flagged", verdict)
    return out


if __name__ == "__main__":
    main()
