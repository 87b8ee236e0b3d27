"""report.html of a real small campaign (OPM Flow, Prefect, Parquet) opened in a real headless
browser (Debian's chromium): every expected figure is on the page, decoded and not one flat
colour; the diagnosis section is there exactly when the campaign has a diagnosis; the
forecast reports the known truth's cumulative oil beside P90/P50/P10. A first reading of the
page finds the best case, its held-back E and tables, which responses carry information (the
rate control and a dry well's water marked, not scored), and the calls as valid, penalised or
failed with the physics checks in words; the same words in report.md and report.json."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from html import unescape
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest
from conftest import cli_env
from test_ui_browser import CHROMIUM

from hmcore.model.case import PhysicsSettings
from hmcore.reporting.calls import STATES
from hmcore.reporting.figures import heatmap_figure
from hmcore.reporting.html import ReportInputs, render
from hmcore.reporting.report import build_report
from hmcore.scenarios.synthetic import ar1_series
from hmcore.scoring.information import information_table, informative_macro
from hmcore.scoring.noise import PUNQ_NOISE
from hmcore.scoring.physics import CHECK_NAMES, Check, check_sentence
from hmflow.console import STATUS_WORDS

CAMPAIGN = "html-check"
BUDGET = 4


def dom(path, width: int = 1300) -> str:
    """The page's DOM after its scripts ran (the figure checks run on window load), in a
    window ``width`` px wide."""
    args = [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
            f"--window-size={width},2000", "--virtual-time-budget=15000", "--dump-dom",
            path.resolve().as_uri()]
    return subprocess.run(args, capture_output=True, text=True, timeout=120, check=True).stdout


LAYOUT_CHECK = """
window.addEventListener("load", function () {
  /* Every visible text box (one per line of each text node: Range.getClientRects) and every
     image; pairs from different nodes that intersect by more than TOL px both ways. */
  var TOL = 2, boxes = [], k = 0, node, images = [];
  var walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  function box(id, b, what) {
    boxes.push({id: id, what: what, x0: b.left + scrollX, x1: b.right + scrollX,
                y0: b.top + scrollY, y1: b.bottom + scrollY});
  }
  while ((node = walker.nextNode())) {
    var el = node.parentElement;
    if (!node.textContent.trim() || !el || el.closest("script, style")) { continue; }
    var st = getComputedStyle(el);
    if (st.visibility !== "visible" || st.opacity === "0") { continue; }
    var range = document.createRange();
    range.selectNodeContents(node);
    var rects = range.getClientRects();
    for (var i = 0; i < rects.length; i++) {
      if (rects[i].width >= 1 && rects[i].height >= 1) {
        box(k, rects[i], el.tagName.toLowerCase() + ' "' + node.textContent.trim().slice(0, 50)
            + '"');
      }
    }
    k++;
  }
  var texts = k;
  document.querySelectorAll("img").forEach(function (img) {
    var b = img.getBoundingClientRect(), name = img.dataset.figure || img.alt || img.src.slice(0, 40);
    images.push({name: name, natural: img.naturalWidth + "x" + img.naturalHeight,
                 loaded: img.complete && img.naturalWidth > 0 && img.naturalHeight > 0,
                 shown: [Math.round(b.width), Math.round(b.height)]});
    box(k++, b, "img " + name);
  });
  boxes.sort(function (a, b) { return a.y0 - b.y0; });
  var overlaps = [];
  for (var i = 0; i < boxes.length; i++) {
    var a = boxes[i];
    for (var j = i + 1; j < boxes.length && boxes[j].y0 < a.y1 - TOL; j++) {
      var c = boxes[j];
      var dx = Math.min(a.x1, c.x1) - Math.max(a.x0, c.x0);
      var dy = Math.min(a.y1, c.y1) - Math.max(a.y0, c.y0);
      if (c.id !== a.id && dx > TOL && dy > TOL) {
        overlaps.push(a.what + " / " + c.what + " (" + Math.round(dx) + " x " + Math.round(dy)
                      + " px)");
      }
    }
  }
  document.body.setAttribute("data-layout", JSON.stringify({
    texts: texts, overlaps: overlaps.slice(0, 20), images: images,
    scroll_width: document.documentElement.scrollWidth, viewport: innerWidth}));
});
"""
"""Run in the page on load: its text boxes that intersect, its images, whether it scrolls
sideways; left as JSON in the body's ``data-layout``."""


def layout(html: str, where, width: int) -> dict:
    """:data:`LAYOUT_CHECK`'s findings on the page ``html`` (written to ``where``, the script
    added before ``</body>``) in a ``width`` px window."""
    where.write_text(html.replace("</body>", f"<script>{LAYOUT_CHECK}</script></body>"),
                     encoding="utf-8")
    found = re.search(r'data-layout="([^"]*)"', dom(where, width))
    assert found, f"the layout check did not run on {where}"
    return json.loads(unescape(found.group(1)))


def figures_on(page: str) -> dict[str, dict[str, str]]:
    """data-figure name -> its data-* attributes as the page's script left them."""
    out = {}
    for tag in re.findall(r"<img [^>]*data-figure=[^>]*>", page):
        attrs = dict(re.findall(r'data-([a-z]+)="([^"]*)"', tag))
        out[attrs.pop("figure")] = attrs
    return out


@pytest.fixture(scope="module")
def campaign(tmp_path_factory, small_case, prefect_api):
    """A real 4-call cmaes campaign on the small synthetic case (cmaes starts at the box's
    centre, which no physics check refuses there, so there is a valid best case), through the
    session's Prefect server."""
    root = tmp_path_factory.mktemp("html")
    store = root / "store"
    run = subprocess.run([sys.executable, "-m", "hmflow.cli", "run", "--case", str(small_case),
                          "--budget", str(BUDGET), "--agent", "cmaes", "--workers", "2",
                          "--campaign", CAMPAIGN, "--storage", str(store)], cwd=root,
                         env=cli_env(prefect_api), capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return store


@pytest.mark.opm
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_every_expected_figure_is_on_the_page_loaded_and_not_blank(campaign):
    from hmcore.reporting.html import expected_figures
    from storage import ArtifactStore
    from tasks.results import report, report_inputs

    store = ArtifactStore(campaign)
    rep = store.latest(CAMPAIGN, "report")
    page = dom(rep.file("report.html"))
    shown = figures_on(page)
    case = store.latest(CAMPAIGN, "case").read_json("case.json")
    results = store.latest(CAMPAIGN, "results")
    inputs = report_inputs(store, CAMPAIGN, case, results.read_parquet("evaluations.parquet"),
                           store.latest(CAMPAIGN, "best").read_json("metrics.json"), None,
                           store.latest(CAMPAIGN, "curves"), None, None, {})
    expected = set(expected_figures(inputs))
    wells = {f"well__{w}.png" for w in case["wells"]}
    assert wells | {"best_so_far.png", "cmatch_heatmap.png", "parameter_traces.png",
                    "parameters_vs_bounds.png", "forecast_fan.png"} <= expected
    assert set(shown) == expected, (sorted(shown), sorted(expected))
    assert all(a.get("loaded") == "yes" and a.get("blank") == "no" for a in shown.values()), shown
    assert all(name in rep.files for name in expected)  # the same figures as PNG beside it
    assert 'id="diagnosis"' not in page  # no diagnosis, no section
    assert "E of the prior centre" in page and "E of the truth" in page
    for table in ("Match by category", "C_match (%) per well and category"):
        assert table in page
    # the report-only rerun rebuilds the same page from the store, no simulator call
    runs_before = sorted((campaign / CAMPAIGN / "runs").iterdir())
    again = report.fn(str(campaign), CAMPAIGN, publish_prefect_artifacts=False)
    assert again.file("report.html").read_text().count("data-figure=") == len(expected)
    assert sorted((campaign / CAMPAIGN / "runs").iterdir()) == runs_before


@pytest.mark.opm
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_no_text_box_overlaps_another_and_every_figure_is_shown(campaign, tmp_path):
    """report.html in chromium at the page's width (1300 px) and in a narrow window (800 px):
    no two visible text boxes (headings, paragraphs, cards, table cells, captions; a box per
    line of text) intersect, no text lies on a figure, every figure is decoded and shown at a
    non-zero size; at 1300 px the page does not scroll sideways. The check itself catches a
    page made to overlap and an image that does not load."""
    from storage import ArtifactStore

    page = ArtifactStore(campaign).latest(CAMPAIGN, "report").file("report.html").read_text(
        encoding="utf-8")
    for width in (1300, 800):
        found = layout(page, tmp_path / f"report-{width}.html", width)
        assert found["texts"] > 100, found  # the page's text, not an empty body
        assert not found["overlaps"], (width, found["overlaps"])
        figures = [i for i in found["images"] if i["name"].endswith(".png")]
        assert len(figures) >= 5, found["images"]
        assert all(i["loaded"] and min(i["shown"]) > 50 for i in found["images"]), \
            (width, found["images"])
        if width == 1300:
            assert found["scroll_width"] <= found["viewport"], found
    bad = ('<html><body><h2 style="position:absolute; top:10px">a heading</h2>'
           '<p style="position:absolute; top:18px; left:30px">a paragraph on it</p>'
           '<img src="no-such-figure.png" alt="missing" style="margin-top:120px"></body></html>')
    caught = layout(bad, tmp_path / "overlapping.html", 800)
    assert len(caught["overlaps"]) == 1 and "a heading" in caught["overlaps"][0], caught
    assert not caught["images"][0]["loaded"], caught


@pytest.mark.opm
@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed")
def test_the_diagnosis_section_appears_when_the_campaign_has_a_diagnosis(campaign, tmp_path):
    """The same campaign with a diagnosis stored (made by the real diagnosis code on the
    linear stand-in of test_diagnosis): the section and its figures appear."""
    from test_diagnosis import Parameter, _linear_case

    from hmcore.diagnosis import diagnose
    from tasks.diagnose import store_step
    from tasks.results import report

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    (tmp_path / "c").mkdir()
    case, sim, _ = _linear_case(tmp_path / "c", hidden, 12.0)
    doc = diagnose(case, sim.evaluate_batch, out_dir=tmp_path / "out")
    files = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    store_step.fn(str(campaign), CAMPAIGN, "diagnosis-report", {"n": 1}, files)
    rep = report.fn(str(campaign), CAMPAIGN, publish_prefect_artifacts=False)
    page = dom(rep.file("report.html"))
    shown = figures_on(page)
    assert 'id="diagnosis"' in page and doc["verdict"].split(".")[0][:40] in page
    diag = {n for n in shown if n.startswith("diagnosis__")}
    assert diag == {f"diagnosis__{p}" for p in doc["plots"]} and diag
    assert all(shown[n].get("loaded") == "yes" and shown[n].get("blank") == "no" for n in diag)


@pytest.mark.opm
def test_the_forecast_reports_the_truths_cumulative_oil_beside_the_band(campaign):
    from hmcore.calibration.loop import best_record
    from hmcore.simulation.curves import FIELD, value_at_end
    from hmcore.simulation.forecast import inside_band
    from storage import ArtifactStore

    curves = ArtifactStore(campaign).latest(CAMPAIGN, "curves")
    table = curves.read_parquet("forecast.parquet")
    doc = curves.read_json("forecast.json")
    assert doc["truth_known"] and doc["kind"] == "near_best" and "NOT a calibrated" in doc["caveat"]
    oil = table[(table.well == FIELD) & (table.quantity == "FOPT")].iloc[0]
    assert oil.P90 <= oil.P50 <= oil.P10 and oil.members == len(doc["member_calls"]) >= 1
    c = curves.read_parquet("curves.parquet")
    truth_run = c[c.member == "truth"]
    assert oil.truth == pytest.approx(value_at_end(truth_run, FIELD, "FOPT"))
    assert oil.truth_inside == inside_band(oil.P90, oil.P10, oil.truth)
    stored = ArtifactStore(campaign).latest(CAMPAIGN, "results").read_json("records.json")
    best = best_record(stored["records"], stored["objective"])  # the campaign's best call
    assert doc["objective"] == stored["objective"] and doc["member_calls"][0] == best["index"] + 1
    assert set(c[c.member == "best"].call) == {best["index"] + 1}  # its curves are the best's
    members = [value_at_end(c[c.member == f"call-{k}"], FIELD, "FOPT")
               for k in doc["member_calls"]]
    assert oil.P50 == pytest.approx(float(np.median(members)))
    assert len(set(pd.unique(c.member))) >= 3  # best, truth, centre (and the members)


# ------------------------------------------------------------------ a first reading of the page
class Page(HTMLParser):
    """A page's text (whitespace collapsed, scripts left out) and its tables, each under the
    last heading before it (rows of cell texts)."""

    def __init__(self, html: str):
        super().__init__()
        self.parts: list[str] = []
        self.tables: list[tuple[str, list[list[str]]]] = []
        self._heading: str | None = None
        self._last_heading = ""
        self._cell: list[str] | None = None
        self._skip = 0
        self.feed(html)
        self.text = " ".join(" ".join(self.parts).split())

    def handle_starttag(self, tag, attrs):
        if tag in ("script", "style"):
            self._skip += 1
        elif tag in ("h1", "h2", "h3"):
            self._heading = ""
        elif tag == "table":
            self.tables.append((self._last_heading, []))
        elif tag == "tr":
            self.tables[-1][1].append([])
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("script", "style"):
            self._skip -= 1
        elif tag in ("h1", "h2", "h3") and self._heading is not None:
            self._last_heading, self._heading = " ".join(self._heading.split()), None
        elif tag in ("td", "th") and self._cell is not None:
            self.tables[-1][1][-1].append(" ".join("".join(self._cell).split()))
            self._cell = None

    def handle_data(self, data):
        if self._skip:
            return
        self.parts.append(data)
        if self._heading is not None:
            self._heading += data
        if self._cell is not None:
            self._cell.append(data)

    def table(self, heading: str) -> list[dict[str, str]]:
        """The first table under ``heading``, as one dict per row keyed by the header."""
        rows = next(rows for head, rows in self.tables if head == heading)
        return [dict(zip(rows[0], r)) for r in rows[1:]]


NUMBER = r"\d+(?:\.\d+)?(?:e[-+]?\d+)?"
"""A number as the page prints it (a sentence's full stop left out)."""


@pytest.mark.opm
def test_a_first_reading_finds_the_best_case_held_back_information_and_calls(campaign,
                                                                              small_case):
    """The facts a new reader needs, read from the built page and checked against the stored
    records and the case's own files (its noise-free truth, its history's sigma)."""
    from storage import ArtifactStore, EvaluationJournal
    from tasks.reference import CENTRE, FLOOR

    store = ArtifactStore(campaign)
    rep = store.latest(CAMPAIGN, "report")
    page = Page(rep.file("report.html").read_text())
    table = store.latest(CAMPAIGN, "results").read_parquet("evaluations.parquet")
    best = store.latest(CAMPAIGN, "best").read_json("metrics.json")
    case = store.latest(CAMPAIGN, "case")
    end = case.read_json("case.json")["fit_history_end_days"]

    # the best case: its E, which call of how many
    m = re.search(rf"({NUMBER}) misfit E of the best call \(call (\d+) of (\d+)\)", page.text)
    assert float(m[1]) == pytest.approx(best["E"], rel=1e-5)
    assert (int(m[2]), int(m[3])) == (best["index"] + 1, len(table))
    # the held-back history: its E and its tables
    m = re.search(rf"Held-back history \(after day ({NUMBER})\): E = ({NUMBER}) \(truth / "
                  rf"deck values ({NUMBER}); prior centre ({NUMBER})\)", page.text)
    assert float(m[1]) == end and float(m[2]) == pytest.approx(best["E_heldout"], rel=1e-5)
    refs = {r["index"]: r for r in EvaluationJournal(store, f"{CAMPAIGN}-reference").rows()}
    assert [float(m[3]), float(m[4])] == pytest.approx(  # its yardsticks: the reference runs'
        [refs[FLOOR]["E_heldout"], refs[CENTRE]["E_heldout"]], abs=5e-7)  # (6 decimals)
    held = {r["category"]: r for r in page.table("Held-back history: categories")}
    for cat, score in best["heldout_metrics"]["categories"].items():
        if score["n"]:
            assert int(held[cat]["N"]) == score["n"]

    # which responses carry information, from the case's files: the oil rate given without
    # sigma is the rate control; a water cut whose noise-free truth stays far within the noise
    # is noise around zero; one that rises well beyond it carries information
    observed = case.read_parquet("observed.parquet")
    oil = observed[observed.quantity == "WOPR"]
    controls = {w for w, g in oil.groupby("well") if g.sigma.isna().all()}
    truth = pd.read_csv(small_case.parent / "truth_responses.csv")
    wct = truth[(truth.quantity == "WWCT") & (truth.days <= end)].groupby("well").value.max()
    dry = set(wct[wct < PUNQ_NOISE.wct_before / 10].index)
    wet = set(wct[wct > 5 * PUNQ_NOISE.wct_before].index)
    assert controls and dry and wet
    grid = {r["well"]: r for r in page.table("Which responses carry information")}
    scores = {r["well"]: r for r in page.table("C_match (%) per well and category")}
    for well in controls:
        assert grid[well]["oil"] == "rate control"
        assert scores[well]["oil"].endswith("(rate control)")
    for well in dry:
        assert grid[well]["wct"] == grid[well]["water"] == "within its noise of zero"
        assert scores[well]["wct"].endswith("(within its noise of zero)")
    for well in wet:
        assert grid[well]["wct"] == grid[well]["water"] == grid[well]["bhp"] == "yes"
        assert "(" not in scores[well]["wct"]
    if controls == set(case.read_json("case.json")["wells"]):  # the macro says it leaves oil out
        assert "left out: oil (rate control at every well)" in page.text
        assert re.search(r"macro C_match over [a-z, ]*: the kinds of response some well's data "
                         r"inform",
                         page.text) and "macro C_match over oil" not in page.text

    # the calls: valid, penalised, failed, and each physics check in words with its count
    state = table.status.value_counts()
    m = re.search(r"(\d+) simulator calls: (\d+) valid, (\d+) penalised, (\d+) failed", page.text)
    assert tuple(map(int, m.groups())) == (len(table), state.get("COMPLETE", 0),
                                           state.get("INVALID", 0), state.get("FAIL", 0))
    checks = {r["physics check"]: int(r["penalised calls"])
              for r in page.table("Calls: valid, penalised, failed")}
    broke = table.loc[table.status == "INVALID", "violation_kinds"].fillna("").str.split(",")
    assert checks == {CHECK_NAMES[k]: int(broke.map(lambda ks, k=k: k.value in ks).sum())
                      for k in Check}
    markdown = rep.file("report.md").read_text()
    doc = json.loads(rep.file("report.json").read_text())
    assert m[0] in markdown and doc["call_states"] == {
        "valid": int(m[2]), "penalised": int(m[3]), "failed": int(m[4])}
    assert not re.search(r"\b(COMPLETE|INVALID)\b|\{'", page.text + markdown)


# ------------------------------------------------------------------ the figures, drawn
def drawn(make, monkeypatch) -> tuple:
    """The figure ``make()`` draws (caught at :func:`hmcore.reporting.figures.png`), drawn
    once, and every text matplotlib drew on it (tick labels outside the view and hidden ones
    are not drawn): (figure, [(text artist, its box in pixels)])."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    from hmcore.reporting import figures

    made, texts, draw = [], [], Text.draw

    def record(self, renderer):
        draw(self, renderer)
        if self.get_visible() and self.get_text().strip():
            texts.append((self, self.get_window_extent(renderer)))

    monkeypatch.setattr(figures, "png", lambda fig: made.append(fig) or b"")
    make()
    monkeypatch.setattr(Text, "draw", record)
    FigureCanvasAgg(made[0])
    made[0].draw_without_rendering()  # lays out and places every artist, paints no pixel
    monkeypatch.undo()
    return made[0], texts


def overlaps(fig, texts) -> list[str]:
    """Pairs that cover each other by more than a pixel both ways: two texts, a legend and a
    text not its own, a panel and a text or a figure legend that is not its own."""
    renderer = fig.canvas.get_renderer()
    legends = [*fig.legends, *(a.get_legend() for a in fig.axes if a.get_legend())]
    panels = [a for a in fig.axes if a.get_visible()]

    def cover(a, b) -> bool:
        return (min(a.x1, b.x1) - max(a.x0, b.x0) > 1) and (min(a.y1, b.y1) - max(a.y0, b.y0) > 1)

    found = [f"{s.get_text()!r} / {t.get_text()!r}" for i, (s, a) in enumerate(texts)
             for t, b in texts[i + 1:] if cover(a, b)]
    for leg in legends:
        box, own = leg.get_window_extent(renderer), set(leg.get_texts())
        found += [f"legend / {t.get_text()!r}" for t, b in texts
                  if t not in own and t is not leg.get_title() and cover(box, b)]
        if leg in fig.legends:
            found += [f"legend / panel {p.get_title()!r}" for p in panels
                      if cover(box, p.get_window_extent(renderer))]
    for p in panels:
        box = p.get_window_extent(renderer)
        found += [f"panel {p.get_title()!r} / {t.get_text()!r}" for t, b in texts
                  if t.axes is not p and t.axes is not None and cover(box, b)]
    return found


def producer_history(days: np.ndarray) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A producer's observed history (a rate control with shut-ins, a water rate and water
    cut of noise about 0, gas, BHP, GOR) and its curves: prior centre, truth, best case."""
    rng = np.random.default_rng(3)
    shut = (days % 365) < 15
    base = {"WOPR": np.where(shut, 0.0, 200.0), "WWPR": np.zeros_like(days),
            "WGPR": np.where(shut, 0.0, 40000 - 5 * days), "WBHP": 190 - 0.02 * days,
            "WGOR": 200 - 0.03 * days, "WWCT": np.zeros_like(days)}
    units = {"WOPR": "SM3/DAY", "WWPR": "SM3/DAY", "WGPR": "SM3/DAY", "WBHP": "BARSA",
             "WGOR": "SM3/SM3", "WWCT": ""}
    sigma = {"WOPR": 0.0, "WWPR": 3.0, "WGPR": 4000.0, "WBHP": 2.0, "WGOR": 20.0, "WWCT": 0.015}
    observed = pd.concat(pd.DataFrame({
        "quantity": q, "days": days, "sigma": sigma[q],
        "observed": np.maximum(v + rng.normal(0, sigma[q] or 1e-9, days.size), 0.0),
        "period": np.where(days > 1900, "heldout", "fit")}) for q, v in base.items())
    curves = pd.concat(pd.DataFrame({
        "well": "PROD1", "member": m, "quantity": q, "days": days, "unit": units[q],
        "value": v * (1.15 if m == "centre" and q != "WOPR" else 1.0)})
        for m in ("centre", "truth", "best") for q, v in base.items())
    return observed, curves


def test_the_figures_have_no_text_on_text_the_truth_on_top_and_axes_that_fit(monkeypatch):
    """Issue 45, item 6, on the figures themselves (PNGs: the browser sees no text in them):
    the best parameters against their bounds (a value near the top row under the title, a
    bound under the legend, before), the well panels (a unit label on the next panel), the
    parameter traces, the fan, best-so-far, failures and the heatmap draw no text over
    another, a legend or another panel; the truth is drawn dashed above the best case it
    matches; a water cut below 0.05 gets an axis of a few percent, not 0-1; the heatmap has no
    column that no well has (injection, without injectors)."""
    from hmcore.reporting import figures as figs

    bounds = {"poro_mult": (0.8, 1.2), "permx_mult": (0.3, 3.0), "permy_mult": (0.3, 3.0),
              "permz_mult": (0.3, 3.0), "skin": (-5.0, 15.0)}
    best = {"poro_mult": 1.078, "permx_mult": 1.61, "permy_mult": 0.5964,
            "permz_mult": 0.4716, "skin": 14.2}
    truth = {"poro_mult": 1.08, "permx_mult": 1.7, "permy_mult": 0.6, "permz_mult": 0.5,
             "skin": 14.0}
    days = np.arange(30.0, 2560.0, 30.0)
    observed, curves = producer_history(days)
    observed.loc[observed.quantity == "WWCT", "observed"] = np.clip(
        observed.loc[observed.quantity == "WWCT", "observed"], 0, 0.045)
    rng = np.random.default_rng(0)
    n = 200
    table = pd.DataFrame({"index": np.arange(n), "status": rng.choice(
        ["COMPLETE", "COMPLETE", "INVALID", "FAIL"], n),
        "E": 0.003 + rng.exponential(0.01, n),
        **{f"p_{k}": rng.uniform(lo, hi, n) for k, (lo, hi) in bounds.items()}})
    table["best_E_so_far"] = table.E.where(table.status == "COMPLETE").cummin().bfill()
    fan = pd.concat(pd.DataFrame({"well": "FIELD", "member": m, "quantity": q, "days": days,
                                  "unit": "SM3", "value": days * scale * (1 + k / 100)})
                    for k, m in enumerate(["truth", "centre", *(f"call-{i}" for i in range(10))])
                    for q, scale in (("FOPT", 650.0), ("FWPT", 50.0), ("FGPT", 9e4)))
    wells = pd.DataFrame({"well": ["PROD1", "PROD2"], "oil": [100.0, 100.0],
                          "water": [50.1, 92.6], "gas": [96.7, 98.8], "bhp": [100.0, 100.0],
                          "water_inj": [np.nan, np.nan]})
    makes = {
        "parameters_vs_bounds": lambda: figs.best_against_bounds(bounds, best, truth),
        "well": lambda: figs.well_curves("PROD1", observed, curves, 1900.0),
        "parameter_traces": lambda: figs.parameter_traces(table, bounds, best),
        "forecast_fan": lambda: figs.forecast_fan(fan, [("FOPT", "field cumulative oil"),
                                                        ("FWPT", "field cumulative water"),
                                                        ("FGPT", "field cumulative gas")],
                                                  1900.0),
        "best_so_far": lambda: figs.best_so_far(table, 0.0029, 0.014),
        "failures": lambda: figs.failures({"failed: no convergence": 3,
                                           "penalised: porosity-permeability trend": 32}),
        "cmatch_heatmap": lambda: figs.cmatch_heatmap(
            wells, {("PROD1", "oil"): "rate control", ("PROD1", "water"): "near zero"})}
    drawn_figures = {}
    for name, make in makes.items():
        fig, texts = drawn(make, monkeypatch)
        assert len(texts) > 5, name
        assert not overlaps(fig, texts), (name, overlaps(fig, texts))
        drawn_figures[name] = fig
    panels = {a.get_title(): a for a in drawn_figures["well"].axes if a.get_visible()}
    for title, ax in panels.items():
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        truth_line, best_line = lines["truth"], lines["best case"]
        assert truth_line.get_zorder() > best_line.get_zorder(), title
        assert truth_line.get_linestyle() != "-", title  # dashed: the best case shows through
    low, high = panels["PROD1: water cut"].get_ylim()
    assert -0.01 < low <= 0 and 0.045 < high < 0.1, (low, high)
    heatmap = drawn_figures["cmatch_heatmap"].axes[0]  # no column of n/a: no injector
    assert [t.get_text() for t in heatmap.get_xticklabels()] == ["oil", "water", "gas", "bhp"]
    fan_truth = [ln for a in drawn_figures["forecast_fan"].axes for ln in a.get_lines()
                 if ln.get_label() == "truth"]
    assert fan_truth and all(ln.get_zorder() > 2 for ln in fan_truth)


def test_a_response_without_information_is_grey_in_the_heatmap_not_coloured():
    wells = pd.DataFrame({"well": ["A", "B"], "oil": [100.0, 100.0], "water": [50.1, 50.2]})
    fig = heatmap_figure(wells, {("A", "oil"): "rate control",
                                 ("A", "water"): "within its noise of zero"})
    coloured = fig.axes[0].images[1].get_array()  # the C_match colour scale
    assert coloured.mask[0, 0] and coloured.mask[0, 1]
    assert not coloured.mask[1, 1] and coloured[1, 1] == 50.2  # B's water: a real miss, red
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert "100.0\nrate control" in texts and "50.1\nzero \u00b1 noise" in texts


def _rows(well: str, quantity: str, values: np.ndarray, sigma: float | np.ndarray,
          source: str = "given") -> pd.DataFrame:
    n = len(values)
    return pd.DataFrame({"well": well, "quantity": quantity, "days": 30.0 * np.arange(1, n + 1),
                         "observed": values, "sigma": sigma, "sigma_source": source,
                         "flowing": True, "period": np.where(np.arange(n) < n - 8, "fit",
                                                             "heldout")})


def test_the_rate_control_and_a_dry_wells_water_carry_no_information():
    """A rate control (oil read as the control, or fixed by the history's control) and noise
    clipped at zero carry none; a water cut that rises, or that stays 2.5 sigma above zero the
    whole time, carries information. The macro leaves out a category none of whose wells
    carries information and says so."""
    rng = np.random.default_rng(3)
    n, s = 40, PUNQ_NOISE.wct_before
    noise = s * ar1_series(rng, n, PUNQ_NOISE.rho)
    rows = pd.concat([
        _rows("A", "WOPR", np.full(n, 150.0), 7.5, "rate"),
        _rows("A", "WWCT", np.clip(noise, 0, 1), s),                    # dry: noise around 0
        _rows("B", "WWCT", np.clip(np.linspace(0, 0.3, n) + noise, 0, 1), s),   # breakthrough
        _rows("C", "WWCT", np.clip(2.5 * s + noise, 0, 1), s),          # small, but steady
        _rows("A", "WBHP", 200 + 3 * noise / s, 3.0)], ignore_index=True)
    controlled = pd.DataFrame({"well": "B", "quantity": "WOPR", "days": [30.0, 1170.0]})
    info = information_table(rows, controlled, history_end=1000.0)
    why = {(r.period, r.well, r.category): r.why for r in info.itertuples()}
    for period in ("fit", "heldout"):
        assert why[(period, "A", "oil")] == why[(period, "B", "oil")] == "rate control"
        assert why[(period, "A", "wct")] == "within its noise of zero"
        for informative in ("B", "wct"), ("C", "wct"), ("A", "bhp"):
            assert why[(period, *informative)] == ""
    assert (~info.informative).sum() == 6  # A's and B's oil, A's water cut, in both periods
    metrics = {"categories": {"oil": {"n": n, "nmse": 0.0, "r2": 1.0},
                              "water": {"n": n, "nmse": 0.2, "r2": 0.5},
                              "bhp": {"n": n, "nmse": 0.01, "r2": 0.9}}}
    macro = informative_macro(metrics, info.assign(category=info.category.replace(
        "wct", "water")), "fit")
    assert macro["includes"] == ["water", "bhp"] and macro["left_out"] == {"oil": "rate control"}
    assert macro["nmse"] == pytest.approx(0.105) and macro["cmatch"] == pytest.approx(100 / 1.105)


def test_calls_and_physics_checks_read_the_same_in_markdown_html_and_json():
    """Hand-made calls: two valid, two penalised (one breaking two checks), two failed (one not
    simulated for an impossible porosity: failed, not penalised). Every page says valid,
    penalised and failed with the same counts, names each check in words with its limit from
    the case's [physics] and counts the calls each penalised; the terminal uses the same words."""
    table = pd.DataFrame({
        "index": range(6), "status": ["COMPLETE", "INVALID", "INVALID", "FAIL", "FAIL",
                                      "COMPLETE"],
        "E": [0.02, 0.015, 0.03, np.nan, np.nan, 0.01],
        "violation_kinds": ["", "poro_perm_trend", "poro_perm_trend,pore_volume", "",
                            "porosity_max", ""],
        "failure": [None, None, None, "no_convergence", "not_runnable", None],
        "p_a": [0.5, 0.6, 0.7, 0.8, 0.9, 0.4], "sim_time_s": 1.0, "wall_time_s": 1.0})
    table["best_E_so_far"] = table.E.where(table.status == "COMPLETE").cummin().ffill()
    physics = {"trend_sd": 2.5, "pore_volume_change_max": 0.1}
    case_doc = {"name": "x", "source": "x.toml", "physics": physics,
                "parameters": [{"name": "a", "low": 0.0, "high": 1.0}]}
    best = {"index": 5, "E": 0.01, "params": {"a": 0.4},
            "metrics": {"macro": {"nmse": 0.1, "r2": 0.5, "cmatch": 90.9}, "categories": {},
                        "wells": {}, "excluded": {}}}
    markdown, doc = build_report("c", case_doc, table, best, None)
    html, _ = render(ReportInputs("c", case_doc, "cmaes", table, best, None, None, None, None,
                                  None))
    page = Page(html).text
    for text in (markdown, page):
        assert "6 simulator calls: 2 valid, 2 penalised, 2 failed" in text
        assert "no convergence 1" in text and "not runnable 1" in text
        assert not re.search(r"\b(COMPLETE|INVALID|FAIL)\b|\{'|hmcore\.", text)
    settings = PhysicsSettings.model_validate(physics)
    penalised = {"poro_perm_trend": 2, "pore_volume": 1}
    for kind in Check:
        row = f"| {CHECK_NAMES[kind]} | {check_sentence(kind.value, settings)} | " \
              f"{penalised.get(kind.value, 0)} |"
        assert row in markdown
        assert f"{CHECK_NAMES[kind]} {check_sentence(kind.value, settings)} " \
               f"{penalised.get(kind.value, 0)}" in page
    assert "2.5 standard deviations" in page and "at most 10 %" in page  # the case's limits
    assert doc["call_states"] == {"valid": 2, "penalised": 2, "failed": 2}
    assert {c["name"]: c["penalised_calls"] for c in doc["physics_checks"]} == {
        CHECK_NAMES[k]: penalised.get(k.value, 0) for k in Check}
    assert dict(STATUS_WORDS) == {state: word for state, word, _ in STATES}
