"""The diagnosis report: ranking table, gain table, residual findings (Markdown), plots, and
the files of a diagnosis (``diagnosis.json``, ``report.md``, one PNG per named well)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from hmcore.diagnosis.decision import statistic_text
from hmcore.model.case import Case
from hmcore.ordering import natural_key
from hmcore.scoring.observations import ObservationSet
from storage.jsonable import to_jsonable

PLOTTED = ("WOPR", "WWPR", "WGPR", "WBHP", "WGOR", "WWCT")
LABELS = {"WOPR": "oil rate", "WWPR": "water rate", "WGPR": "gas rate", "WBHP": "BHP",
          "WGOR": "GOR", "WWCT": "water cut (fraction)"}


def _f(v, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if isinstance(v, (int, np.integer)):
        return str(v)
    v = float(v)
    return f"{v:.{digits}g}"


def _unexplained(doc: dict, h2: str) -> list[str]:
    """Where the calibrated model misses beyond noise, when that is the answer."""
    first = doc["causes"][0] if doc["causes"] else {}
    if first.get("kind") != "unexplained":
        return []
    lines = [f"{h2} Unexplained: where the model misses", "", first["evidence"] + ".", "",
             "| well | response | period | days | bias (data units) | z bias | z trend |",
             "|---|---|---|---|---|---|---|"]
    for f in first.get("where", []):
        d0, d1 = f["days"]
        lines.append(f"| {f['well']} | {f['response']} | {f['period']} | {_f(d0, 5)}-"
                     f"{_f(d1, 5)} | {_f(f['bias'], 4)} | {f['z_bias']:+.1f} | "
                     f"{f['z_trend']:+.1f} |")
    return lines + [""]


def _accepted(doc: dict, h2: str) -> list[str]:
    """Each accepted cause with its own gain (over the model without it), and what the second
    round of the forward selection did."""
    acc = doc.get("accepted") or []
    lines = []
    if acc:
        lines += [f"{h2} Accepted causes", "",
                  "Each gain is over the model without that cause (round 2: with round 1's "
                  "cause in the model).", "",
                  "| round | cause | value | fitted E before | after | held-back E before | "
                  "after | fitted SSR drop | held-back SSR drop |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for a in acc:
            g = a["gain"]
            lines.append(f"| {a['round']} | {a['id']} - {a['description']} | {_f(a['value'])} | "
                         f"{_f(g['fit_before'], 5)} | {_f(g['fit_after'], 5)} | "
                         f"{_f(g['heldout_before'], 5)} | {_f(g['heldout_after'], 5)} | "
                         f"{_f(a['delta_ssr_fit'], 5)} | {_f(a['delta_ssr_heldout'], 5)} |")
        lines.append("")
    for r in doc.get("rounds") or []:
        lines += [f"Round 2 ({r['simulations']} simulations, "
                  f"{'tentatively ' if r['tentative'] else ''}with `{r['builds_on']}` in the "
                  f"model): {r['verdict']}", ""]
    if doc.get("no_second_round") and acc:
        lines += [f"No second round: {doc['no_second_round']}.", ""]
    return lines


def _windows(doc: dict, h2: str) -> list[str]:
    """The fitted windows diagnosed, in time order, and which named the answer."""
    wins = doc.get("windows") or []
    if not wins:
        why = doc.get("no_later_window")
        return ([f"No later fitted window: {why}.", ""]
                if why and not doc.get("accepted") else [])
    named = (doc.get("named_on") or {}).get("fitted_to_day")
    lines = [f"{h2} Fitted windows (rolling origin)", "",
             "| history fitted to day | accepted | first cause | held-back fitted within noise "
             "| named the answer |", "|---|---|---|---|---|"]
    for w in wins:
        lines.append(f"| {_f(w['fitted_to_day'], 6)} | {', '.join(w['accepted']) or '-'} | "
                     f"{w['first_cause'] or '-'} | "
                     f"{'yes' if w['heldout_within_noise'] else 'no'} | "
                     f"{'yes' if named == w['fitted_to_day'] else ''} |")
    lines.append("")
    if doc.get("no_further_window"):
        lines += [f"No further window: {doc['no_further_window']}.", ""]
    return lines


def ranking_table(doc: dict, most: int = 15) -> str:
    lines = ["| rank | kind | wells | layers | score | chi2 | evidence | description |",
             "|---|---|---|---|---|---|---|---|"]
    for n, c in enumerate(doc["causes"][:most], 1):
        lines.append(f"| {n} | {c['kind']} | {', '.join(c['wells']) or '-'} | "
                     f"{', '.join(map(str, c['layers'])) or '-'} | {_f(c['score'], 3)} | "
                     f"{_f(c['chi2'], 4)} | {c.get('evidence', '')} | {c['description']} |")
    return "\n".join(lines)


def answer_lines(doc: dict, h2: str, most: int = 10) -> list[str]:
    """The answer by the evidence (:mod:`hmcore.diagnosis.answer`): one cause or the set the
    data cannot separate, the weight of each explanation and what would separate the set's
    members. Empty for a diagnosis stored before it was weighed."""
    a = doc.get("answer")
    if not a or not a.get("explanations"):
        return []
    lines = [f"{h2} The answer, by the evidence", "", a["text"][0].upper() + a["text"][1:] + ".",
             "",
             f"Weights: the softmax of each explanation's log evidence (Laplace approximation "
             f"from its fit's Jacobian; BIC for terms without one; the held-back history's "
             f"predictive likelihood added), the answer the smallest set carrying "
             f"{100 * a['mass']:.0f} % of the weight"
             + (f"; SSRs read with the noise variance inflated {a['scale']:.2f}x (the best "
                "fit leaves that much more than noise)" if a.get("scale", 1.0) > 1.0 else "")
             + ".", "",
             "| explanation | weight | log evidence | log likelihood | log Occam | parameters "
             "| fitted SSR | held-back SSR | fitted E | held-back E |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for x in a["explanations"][:most]:
        mark = " **(in the answer)**" if x["id"] in a["members"] else ""
        lines.append(f"| {x['id']}{mark} | {x['weight']:.3f} | {x['log_evidence']:.1f} | "
                     f"{x['log_likelihood']:.1f} | {x['log_occam']:.1f} | "
                     f"{x['n_parameters']} ({x['method']}) | {_f(x['ssr_fit'], 6)} | "
                     f"{_f(x['ssr_heldout'], 6)} | {_f(x['fit_E'])} | {_f(x['heldout_E'])} |")
    if a.get("separations"):
        lines += ["", "What would separate them:", ""] + [f"- {s['sentence']}"
                                                          for s in a["separations"]]
    return lines + [""]


def _points(gain: dict, period: str) -> str:
    n, m = gain[f"n_{period}"], gain.get(f"n_{period}_measured")
    return f"{n} points" if m is None else f"{n} points, {m} measured: noise alone ~{m}"


def gain_table(doc: dict) -> str:
    g = doc["gain"]
    lines = ["| misfit | before | after |", "|---|---|---|",
             f"| E, fitted history | {_f(g['fit_before'], 5)} | {_f(g['fit_after'], 5)} |",
             f"| E, held-back history | {_f(g['heldout_before'], 5)} | "
             f"{_f(g['heldout_after'], 5)} |",
             f"| whitened SSR, fitted ({_points(g, 'fit')}) | {_f(g['ssr_fit_before'], 6)} | "
             f"{_f(g['ssr_fit_after'], 6)} |",
             f"| whitened SSR, held back ({_points(g, 'heldout')}) | "
             f"{_f(g['ssr_heldout_before'], 6)} | {_f(g['ssr_heldout_after'], 6)} |"]
    return "\n".join(lines)


def recalibration_table(doc: dict) -> str:
    """Each recalibrated candidate: its value, the fitted and held-back whitened SSR after, and
    what the restart from the deck's values did."""
    lines = ["| candidate | value | fitted SSR after | held-back SSR after | runs | restart from "
             "the deck's values |", "|---|---|---|---|---|---|"]
    for cid, c in doc.get("candidates_recalibrated", {}).items():
        r = c.get("restart")
        restart = "-" if not r else (f"{'accepted' if r['accepted'] else 'not used'}: SSR "
                                     f"{_f(r['ssr_fit'], 6)} vs warm {_f(r['ssr_fit_warm'], 6)}"
                                     f" ({r.get('reason', '')})")
        lines.append(f"| {cid} | {_f(c['value'])} | {_f(c['ssr_fit_after'], 6)} | "
                     f"{_f(c['ssr_heldout_after'], 6)} | {c['runs']} | {restart} |")
    return "\n".join(lines)


def well_table(doc: dict) -> str:
    pw = doc["per_well_response"]
    lines = [f"Extension shown: `{pw['extension'] or 'none'}`", "",
             "| well | response | fitted before | fitted after | held back before | "
             "held back after |", "|---|---|---|---|---|---|"]
    for r in pw["rows"]:
        lines.append(f"| {r['well']} | {r['response']} | {_f(r['fit_before'])} | "
                     f"{_f(r['fit_after'])} | {_f(r['heldout_before'])} | "
                     f"{_f(r['heldout_after'])} |")
    return "\n".join(lines)


def markdown_report(doc: dict, level: int = 1) -> str:
    """The diagnosis as Markdown; ``level`` is the level of its title (2 inside a campaign
    report, whose sections move down with it). Plots are linked by file name."""
    sel = doc.get("selected")
    h1, h2 = "#" * level, "#" * (level + 1)
    lines = [f"{h1} Diagnosis of case `{doc['case']}`", "",
             "Calibrated parameters: " + ", ".join(f"{k} = {_f(v)}"
                                                     for k, v in doc["calibrated"].items())
             + f"; history fitted up to day {_f(doc['history_end_days'], 6)}, later data held "
             "back.", "", f"{h2} Verdict", "", doc["verdict"], "",
             "Selected extension: " + (f"**{sel['kind']}** ({sel['id']}) - {sel['description']}"
                                       if sel else "**none**"), "",
             ] + answer_lines(doc, h2) + _accepted(doc, h2) + _windows(doc, h2) + [
             f"{h2} Gain", "", gain_table(doc), ""] + (
             [f"{h2} The statistic", "", statistic_text(doc["statistic"]) + ".", ""]
             if "statistic" in doc else []) + [f"{h2} Ranked causes", "",
             ranking_table(doc), ""] + _unexplained(doc, h2) + [
             f"{h2} Recalibrated candidates", "",
             "Before: fitted SSR " + _f(doc["gain"]["ssr_fit_before"], 6) + ", held-back SSR "
             + _f(doc["gain"]["ssr_heldout_before"], 6) + ".", "", recalibration_table(doc), "",
             f"{h2} Misfit per well and response (E contributions)", "",
             well_table(doc), "", f"{h2} Residual findings beyond noise (calibrated model)", ""]
    flags = doc["residuals"].get("flags", [])
    lines += [f"- {f['text']}" for f in flags[:40]] or ["- none"]
    if len(flags) > 40:
        lines.append(f"- ... and {len(flags) - 40} more")
    if doc.get("plots"):
        lines += ["", f"{h2} Plots", ""] + [f"![{p}]({p})" for p in doc["plots"]]
    cost = doc.get("cost", {})
    lines += ["", f"Cost: {cost.get('simulations')} simulations, "
                  f"{_f(cost.get('wall_time_s'), 4)} s wall time.", ""]
    return "\n".join(lines)


def plot_wells(obs: ObservationSet, base: pd.DataFrame, extended: pd.DataFrame | None,
               wells: list[str], out_dir: Path, label: str = "") -> list[Path]:
    """One PNG per well: observed vs calibrated vs extended BHP, GOR and water cut."""
    import matplotlib  # slow to import, and only a report with plots needs it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    rows = obs.rows
    for well in wells:
        fig, grid = plt.subplots(3, 2, figsize=(11, 8.5), sharex=True)
        axes = grid.T.flatten()  # rates down the left column, BHP / GOR / WCT on the right
        for ax, q in zip(axes, PLOTTED):
            o = rows[(rows.well == well) & (rows.quantity == q)]
            if q in ("WGOR", "WWCT"):
                o = o[o.flowing]
            y, s = o.observed.to_numpy(float), np.nan_to_num(o.sigma.to_numpy(float))
            low = np.minimum(s, np.maximum(y, 0.0))  # bars stop at 0 (rates, ratios, cut)
            high = np.minimum(s, 1.0 - y) if q == "WWCT" else s  # and a water cut at 1
            ax.errorbar(o.days, y, yerr=[low, np.maximum(high, 0.0)], fmt="o", ms=3,
                        color="k", alpha=0.6, elinewidth=0.6, label="observed")
            for resp, name, style in ((base, "calibrated", "C0-"),
                                      (extended, f"extended {label}".strip(), "C3-")):
                if resp is None:
                    continue
                s = resp[(resp.well == well) & (resp.quantity == q)].sort_values("days")
                if q in ("WGOR", "WWCT"):  # not defined while the well is shut
                    oil = resp[(resp.well == well) & (resp.quantity == "WOPR")]
                    s = s[s.days.isin(oil.days[oil.value > 0])]
                elif q == "WBHP":  # a summary reports BHP 0 before the well exists
                    s = s[s.value > 0]
                ax.plot(s.days, s.value, style, lw=1.4, label=name)
            if obs.history_end_days is not None:
                ax.axvline(obs.history_end_days, color="gray", ls="--", lw=1)
            ax.set_ylabel(LABELS[q])
            ax.grid(alpha=0.3)
        what = "calibrated and extended" if extended is not None else "calibrated"
        fig.suptitle(f"{well}: observed vs {what} model (dashed: end of fitted history)",
                     fontsize=10)
        axes[0].legend(fontsize=8, loc="best")
        for ax in grid[-1]:
            ax.set_xlabel("days")
        fig.tight_layout()
        safe = "".join(ch if ch.isalnum() else "_" for ch in well)
        path = Path(out_dir) / f"residuals_{safe}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        out.append(path)
    return out


def plotted_wells(doc: dict, case: Case) -> list[str]:
    """The wells the answer names: the first cause's and, when it is `unexplained` (or a
    partial answer led by it), the accepted causes' too; every well when they name none."""
    wells: list[str] = []
    for c in doc["causes"]:
        if c["kind"] != "none":
            wells += list(c["wells"])
            break
    for a in doc.get("accepted") or []:
        wells += list(a.get("wells") or [])
    return (sorted(set(wells), key=natural_key) if wells
            else sorted(case.info.wells, key=natural_key))


def write_report(out_dir: Path, doc: dict, case: Case, obs: ObservationSet,
                 base: pd.DataFrame | None, extended: pd.DataFrame | None,
                 plots: bool = True) -> dict[str, Any]:
    """Write ``diagnosis.json`` and ``report.md`` of ``doc`` into ``out_dir`` and, with
    ``plots``, the residual plots of :func:`plotted_wells` (observed, with the noise model
    ``obs``, against the calibrated responses ``base`` and the extended ones ``extended``).
    Sets ``doc["plots"]`` (their file names); returns the paths written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    pngs = []
    if plots:
        shown = doc["per_well_response"]["extension"]
        pngs = plot_wells(obs, base, extended, plotted_wells(doc, case), out_dir,
                          label=shown or "")
    doc["plots"] = [p.name for p in pngs]
    (out_dir / "diagnosis.json").write_text(
        json.dumps(to_jsonable(doc, "diagnosis.json"), indent=2))
    (out_dir / "report.md").write_text(markdown_report(doc))
    return {"diagnosis": out_dir / "diagnosis.json", "report": out_dir / "report.md",
            "plots": pngs}
