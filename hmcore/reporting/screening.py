"""What a person reads of a screening (``hmflow screen``): the ranked table as Markdown, a
tornado chart per response (matplotlib, as the campaign's figures are drawn:
:func:`hmcore.reporting.figures.png`), and the screening's self-contained ``report.html``
(figures inlined, Markdown rendered by :func:`hmcore.reporting.html.markdown_html`).

OAT's tornado is the classic one: per parameter, the response's change from the centre with
the parameter at its low bound and at its high bound, widest swing on top. Morris's and
Sobol''s charts are the same bars of their importance (mu* with sigma beside it; ST with S1
inside it), strongest on top.
"""

from __future__ import annotations

import base64
import html as html_text

import pandas as pd
from matplotlib.figure import Figure

from hmcore.calibration.sensitivity import OVERALL, ScreenMethod
from hmcore.reporting.figures import png
from hmcore.reporting.html import markdown_html

COLUMNS = {ScreenMethod.OAT: ("low", "high", "swing"),
           ScreenMethod.MORRIS: ("mu_star", "mu_star_conf", "sigma", "mu"),
           ScreenMethod.SOBOL: ("S1", "S1_conf", "ST", "ST_conf")}
"""The method's columns of the ranked table, beside parameter, rank and share."""


def response_title(response: str, objective: str = "") -> str:
    """``misfit:PROD1:WBHP`` -> ``PROD1 WBHP: whitened misfit``, and so on; ``objective``: the
    case's objective's name (likelihood or E)."""
    if response in OVERALL:
        return {"objective": f"the case's objective ({objective})" if objective
                else "the case's objective",
                "E": "misfit E"}[response]
    kind, well, quantity = response.split(":", 2)
    what = {"misfit": "whitened misfit (mean square, fitted history)",
            "end": "value at the history end"}[kind]
    return f"{well} {quantity}: {what}"


def markdown_table(table: pd.DataFrame, method: ScreenMethod, response: str) -> str:
    """One response's rows as a Markdown table (parameter, rank, the method's columns,
    share of the strongest)."""
    rows = table[table.response == response]
    cols = ["parameter", "rank", *COLUMNS[method], "share"]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in rows.iterrows():
        cells = [str(r.parameter), str(int(r["rank"]))]
        cells += [f"{float(r[c]):.4g}" for c in COLUMNS[method]]
        cells.append(f"{float(r.share):.1%}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def ranking_markdown(name: str, table: pd.DataFrame, method: ScreenMethod, design: dict,
                     rule: str, chosen: tuple[str, ...], case_file: str | None,
                     skipped: list[str], objective: str = "") -> str:
    """The screening's Markdown: what was run, the rule and its choice, the overall tables
    first, then one per response."""
    lines = [f"# Screening {name}", "",
             f"Method **{method.value}**, {design['calls']} simulator calls, seed "
             f"{design['seed']}" + (f", from the {design['centre']} centre"
                                    if design.get("centre") else "")
             + (f", {design['trajectories']} trajectories on "
                                    f"{design['levels']} levels" if design.get("trajectories")
                                    else "")
             + (f", Sobol' base sample N = {design['base_n']}" if design.get("base_n") else "")
             + ".", "",
             f"**Rule:** a parameter matters when its {rule}.", "",
             f"**Switched on:** {', '.join(chosen) or 'none'}"
             + (f" (new case file: `{case_file}`)" if case_file else "") + ".", ""]
    if skipped:
        lines += [(f"Not ranked (a failed call, or no change over the design): "
                   f"{', '.join(skipped)}."), ""]
    responses = list(dict.fromkeys(table.response))
    ordered = [r for r in OVERALL if r in responses] + [r for r in responses if r not in OVERALL]
    for response in ordered:
        lines += [f"## {response_title(response, objective)}", "",
                  markdown_table(table, method, response)]
    return "\n".join(lines)


def tornado(table: pd.DataFrame, method: ScreenMethod, response: str,
            objective: str = "") -> bytes:
    """One response's tornado (OAT) or importance bars (Morris, Sobol'), strongest on top."""
    rows = table[table.response == response].iloc[::-1]
    fig = Figure(figsize=(6.0, 0.35 * len(rows) + 1.2))
    ax = fig.subplots()
    y = range(len(rows))
    if method is ScreenMethod.OAT:
        ax.barh(y, rows["low"], color="tab:blue", label="at its low bound")
        ax.barh(y, rows["high"], color="tab:orange", label="at its high bound")
        ax.axvline(0.0, color="black", lw=0.8)
        ax.set_xlabel("change from the centre")
    elif method is ScreenMethod.MORRIS:
        ax.barh(y, rows["mu_star"], xerr=rows["mu_star_conf"], color="tab:blue",
                label="mu* (95 % bootstrap interval)")
        ax.plot(rows["sigma"], list(y), "k|", ms=12, label="sigma")
        ax.set_xlabel("mu* (mean |elementary effect|)")
    else:
        ax.barh(y, rows["ST"], xerr=rows["ST_conf"], color="tab:blue",
                label="ST (95 % interval)")
        ax.barh(y, rows["S1"].clip(lower=0), height=0.4, color="tab:orange", label="S1")
        ax.set_xlabel("Sobol' index")
    ax.set_yticks(list(y), rows["parameter"])
    ax.set_title(response_title(response, objective), fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    return png(fig)


def figure_name(response: str) -> str:
    return "tornado__" + response.replace(":", "__") + ".png"


def figures(table: pd.DataFrame, method: ScreenMethod, objective: str = "") -> dict[str, bytes]:
    """Every response's chart by its file name, the overall ones first."""
    responses = list(dict.fromkeys(table.response))
    ordered = [r for r in OVERALL if r in responses] + [r for r in responses if r not in OVERALL]
    return {figure_name(r): tornado(table, method, r, objective) for r in ordered}


def report_html(markdown: str, pngs: dict[str, bytes]) -> str:
    """The self-contained page: the Markdown (rule, choice, tables) then every chart inlined."""
    imgs = "\n".join(
        f'<figure><img data-figure="{n}" alt="{html_text.escape(n)}" '
        f'src="data:image/png;base64,{base64.b64encode(b).decode("ascii")}"></figure>'
        for n, b in pngs.items())
    return ("<!doctype html><html><head><meta charset=\"utf-8\"><title>screening</title>"
            "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
            "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px}"
            "figure{display:inline-block;margin:4px}</style></head><body>"
            f"{markdown_html(markdown)}<h2>Charts</h2>{imgs}</body></html>")
