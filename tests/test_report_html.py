"""report.html of a real small campaign (OPM Flow, Prefect, Parquet) opened in a real headless
browser (Debian's chromium): every expected figure is on the page, decoded and not one flat
colour; the diagnosis section is there exactly when the campaign has a diagnosis; the
forecast reports the known truth's cumulative oil beside P90/P50/P10."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from conftest import cli_env
from test_ui_browser import CHROMIUM

CAMPAIGN = "html-check"
BUDGET = 4


def dom(path) -> str:
    """The page's DOM after its scripts ran (the figure checks run on window load)."""
    args = [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu",
            "--window-size=1300,2000", "--virtual-time-budget=15000", "--dump-dom",
            path.resolve().as_uri()]
    return subprocess.run(args, capture_output=True, text=True, timeout=120, check=True).stdout


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
    from hmcore.simulation.curves import FIELD, value_at_end
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
    assert oil.truth_inside == bool(oil.P90 <= oil.truth <= oil.P10)
    members = [value_at_end(c[c.member == f"call-{k}"], FIELD, "FOPT")
               for k in doc["member_calls"]]
    assert oil.P50 == pytest.approx(float(np.median(members)))
    assert len(set(pd.unique(c.member))) >= 3  # best, truth, centre (and the members)
