"""Identifiability after a campaign (issue 44): the Laplace approximation against cases whose
answer is known (a linear model: its posterior covariance exactly, its 95 % intervals holding
the truth 95 % of the time; two parameters acting only through their product flagged as a
pair; a parameter that moves no residual flagged as not informed), the stencil found among
journaled calls, and the report's section on a real least-squares campaign (OPM Flow, Prefect):
its numbers recomputed with the campaign's own objective, and the words when there is no
Jacobian."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import cli_env

from hmcore.model.parameters import Parameter, Scaling
from hmcore.reporting.identifiability import (
    Finding,
    assess,
    identifiability_markdown,
    pair_sentences,
    uninformed_sentences,
)
from hmcore.scoring.identifiability import (
    PAIR_CORRELATION,
    Z95,
    find_stencil,
    identifiability,
    laplace,
    stencil_jacobian,
)


def params(*specs) -> list[Parameter]:
    """Parameters (name, low, high, log) of kind skin (the kind does not matter here)."""
    return [Parameter(name=n, kind="skin", low=float(lo), high=float(hi), log=log)
            for n, lo, hi, log in specs]


def stencil_of(residuals, u0: np.ndarray, steps: np.ndarray):
    """Journaled points of a forward-difference stencil at ``u0`` (plus two unrelated points)
    and each point's residuals under the function ``residuals``."""
    d = u0.size
    pts = [u0 + np.array([0.3] * d), u0] + [u0 + np.eye(d)[k] * steps[k] for k in range(d)]
    pts.append(u0 - np.array([0.4] * d))
    pts = np.clip(np.array(pts), -1, 1)
    return pts, [residuals(p) for p in pts]


# ------------------------------------------------------------------ the mathematics
def test_a_linear_model_has_its_exact_posterior_and_its_intervals_cover_the_truth():
    """r(u) = G u - y with y = G u_true + e, e ~ N(0, I): the posterior of u is Gaussian with
    covariance (G^T G)^-1 exactly. The forward-difference Jacobian from journaled calls is G
    (one step taken the other way), the covariance is its inverse, the physical sd is the
    scaled one times half the range, and over 2000 noise draws the 95 % intervals hold the
    truth 95 % of the time (binomial sd 0.5 %)."""
    rng = np.random.default_rng(7)
    n, d = 60, 3
    G = rng.normal(size=(n, d)) * np.array([20.0, 8.0, 40.0])
    space = params(("a", 0.5, 1.5, False), ("b", -2.0, 4.0, False), ("c", 10.0, 30.0, False))
    scaling = Scaling.of(space)
    u_true = np.array([0.1, -0.2, 0.05])
    y = G @ u_true + rng.normal(size=n)
    u_hat = np.linalg.lstsq(G, y, rcond=None)[0]
    pts, res = stencil_of(lambda u: G @ u - y, u_hat, np.array([0.05, -0.05, 0.1]))
    st = find_stencil(pts, np.ones(len(pts), bool), 1)
    assert st.base == 1 and st.runs == (2, 3, 4) and st.distance == 0
    J = stencil_jacobian(res[st.base], [res[j] for j in st.runs], st.steps)
    np.testing.assert_allclose(J, G, rtol=1e-8)
    post = laplace(J, res[1])
    exact = np.linalg.inv(G.T @ G)
    np.testing.assert_allclose(post.covariance, exact, rtol=1e-8)
    np.testing.assert_allclose(post.sd, np.sqrt(np.diag(exact)), rtol=1e-8)
    np.testing.assert_allclose(post.correlation,
                               exact / np.sqrt(np.outer(np.diag(exact), np.diag(exact))),
                               atol=1e-10)
    assert post.rank == 3 and post.n == n and not post.undetermined.any()
    found = identifiability("abc", scaling, u_hat, post)
    np.testing.assert_allclose(found.sd, post.sd * np.array([0.5, 3.0, 10.0]), rtol=1e-10)
    np.testing.assert_allclose(found.high - found.low, 2 * Z95 * found.sd, rtol=1e-8)
    assert not found.pairs and not found.uninformed and not found.clipped_low.any()

    truth = scaling.to_values(u_true)
    inside, s2 = 0, []
    for _ in range(2000):
        y = G @ u_true + rng.normal(size=n)
        u_hat = np.linalg.lstsq(G, y, rcond=None)[0]
        post = laplace(G, G @ u_hat - y)
        found = identifiability("abc", scaling, u_hat, post)
        inside += int(((found.low <= truth) & (truth <= found.high)).sum())
        s2.append(post.s2)
    covered = inside / (2000 * d)
    assert 0.935 <= covered <= 0.965, covered
    assert np.mean(s2) == pytest.approx(1.0, abs=0.02)  # chi2 / (n - d): the noise is right


def test_a_log_scaled_parameter_gets_its_factor_and_an_interval_symmetric_in_log():
    """A parameter in [0.1, 10] on a log scale, at the box's centre (value 1) with a scaled sd
    of 0.1: half its log-range is ln(100) / 2, so its sd is the factor 10^0.1, its interval
    [10^-0.196, 10^0.196], and its delta-method sd ln(10) * 0.1."""
    space = params(("k", 0.1, 10.0, True))
    post = laplace(np.array([[10.0]]), np.zeros(1))
    found = identifiability(["k"], Scaling.of(space), np.zeros(1), post)
    assert found.factor[0] == pytest.approx(10 ** 0.1)
    assert found.best[0] == pytest.approx(1.0)
    assert (found.low[0], found.high[0]) == pytest.approx((10 ** -(Z95 * 0.1), 10 ** (Z95 * 0.1)))
    assert found.sd[0] == pytest.approx(np.log(10) * 0.1)


def test_two_parameters_acting_only_through_their_product_are_reported_as_a_pair():
    """The responses depend on a * b (both log-scaled over the same range, so their scaled
    coordinates enter as a sum) and on c: J^T J is singular along (1, -1, 0). The pair is
    flagged with correlation -1, neither is informed alone, and c keeps the sd of the model
    with a and b merged into one parameter."""
    rng = np.random.default_rng(3)
    space = params(("a", 0.5, 2.0, True), ("b", 0.5, 2.0, True), ("c", 0.0, 1.0, False))
    g, h = rng.normal(size=(2, 40)) * 5
    y = rng.normal(size=40)

    def residuals(u):
        a, b, c = Scaling.of(space).to_values(u)
        return g * np.log(a * b) + h * c - y

    pts, res = stencil_of(residuals, np.array([0.1, -0.1, 0.2]), np.full(3, 0.05))
    st = find_stencil(pts, np.ones(len(pts), bool), 1)
    J = stencil_jacobian(res[st.base], [res[j] for j in st.runs], st.steps)
    post = laplace(J, res[1])
    found = identifiability(["a", "b", "c"], Scaling.of(space), pts[1], post)
    assert post.rank == 2 and list(post.undetermined) == [True, True, False]
    assert [(i, j) for i, j, _ in found.pairs] == [(0, 1)]
    assert found.pairs[0][2] == pytest.approx(-1.0)
    assert found.uninformed == (0, 1) and np.isinf(found.sd[:2]).all()
    assert (found.low[0], found.high[0]) == pytest.approx((0.5, 2.0))  # the whole box
    merged = np.linalg.inv(J[:, [0, 2]].T @ J[:, [0, 2]])
    assert post.sd[2] == pytest.approx(np.sqrt(merged[1, 1]), rel=1e-6)
    (said,) = pair_sentences(found)
    assert said.startswith("a and b trade off (correlation -1.00): the data fix their "
                           "combination, not each")


def test_a_strong_but_separable_correlation_is_not_a_pair():
    """Columns at 60 degrees (correlation of the estimates -0.5): below the threshold."""
    J = np.array([[1.0, 0.5], [0.0, np.sqrt(0.75)]]) * 10
    post = laplace(J, np.zeros(2))
    assert post.correlation[0, 1] == pytest.approx(-0.5)
    assert abs(post.correlation[0, 1]) < PAIR_CORRELATION
    found = identifiability(["p", "q"], Scaling.of(params(("p", 0, 1, False),
                                                          ("q", 0, 1, False))), np.zeros(2), post)
    assert not found.pairs


def test_a_parameter_the_data_do_not_move_is_not_informed_and_a_weak_one_is_clipped():
    """Column 0 is zero (the parameter moves no residual): undetermined, its interval the
    whole box. Column 1 gives a scaled sd of 0.5 at u = 0.8: its interval [0.8 - 0.98, 1] is
    cut at the high bound and covers 59 % of the range, more than half: not informed. Column 2
    (scaled sd 0.01) is."""
    J = np.zeros((3, 3))
    J[1, 1], J[2, 2] = 1 / 0.5, 1 / 0.01
    space = params(("dead", 0, 1, False), ("weak", 0, 1, False), ("sharp", 0, 1, False))
    post = laplace(J, np.zeros(3))
    found = identifiability([p.name for p in space], Scaling.of(space),
                            np.array([0.0, 0.8, -0.5]), post)
    assert list(post.undetermined) == [True, False, False]
    assert found.uninformed == (0, 1)
    assert (found.low[0], found.high[0]) == (0.0, 1.0) and found.share[0] == 1.0
    assert found.clipped_high[1] and not found.clipped_low[1] and found.high[1] == 1.0
    assert found.share[1] == pytest.approx((1.0 - (0.8 - Z95 * 0.5)) / 2)
    assert found.sd[1] == pytest.approx(0.25) and found.sd[2] == pytest.approx(0.005)
    said = uninformed_sentences(found)
    assert said[0].startswith("dead: the data do not inform it (no combination")
    assert said[1] == "weak: the data do not inform it (its 95 % interval covers 59 % of its range)."


def test_the_stencil_stands_at_the_nearest_call_that_has_one():
    """The best call (1) has a finite-difference neighbour along the first coordinate only;
    call 0, one step away, has one along each: the Jacobian stands there. A failed run is no
    neighbour, and a base beyond reach is none."""
    b = np.array([0.2, 0.2])
    pts = np.array([b, b + [0.05, 0], b + [0, 0.05], [0.9, -0.9]])
    usable = np.ones(len(pts), bool)
    st = find_stencil(pts, usable, 1)
    assert (st.base, st.runs, st.distance) == (0, (1, 2), pytest.approx(0.05))
    assert st.steps == pytest.approx((0.05, 0.05))
    assert find_stencil(pts, usable, 0).distance == 0
    assert find_stencil(pts, usable, 3) is None
    usable[2] = False
    assert find_stencil(pts, usable, 1) is None


def test_the_section_says_how_to_get_a_jacobian_when_the_journal_has_none():
    """A journal of scattered calls (as random search or CMA-ES leave): not computed, why, and
    the least-squares command for the case."""
    rng = np.random.default_rng(1)
    records = [{"index": i, "action": list(rng.uniform(-1, 1, 2)), "status": "COMPLETE",
                "residuals": list(rng.normal(size=5))} for i in range(6)]
    parameters = [p.model_dump() for p in params(("p", 0, 1, False), ("q", 0, 1, False))]
    finding = assess(records, parameters, 3, None, agent="cmaes")
    assert finding.result is None and finding.best_index == 3
    text = "\n".join(identifiability_markdown(finding, "/data/my case.toml"))
    assert "Not computed. Identifiability needs the Jacobian" in text
    assert "from call 4 or from a call within 0.1 of it" in text
    assert "this campaign's method (cmaes) computed none there" in text
    assert "`hmflow run --case '/data/my case.toml' --agent lm`" in text
    # the same journal with a stencil around call 4 (two more calls): computed there
    x = np.array(records[3]["action"])
    for k in range(2):
        records.append({"index": 6 + k, "action": list(x + np.eye(2)[k] * 0.05),
                        "status": "COMPLETE", "residuals": list(rng.normal(size=5))})
    finding = assess(records, parameters, 3, None)
    assert isinstance(finding, Finding) and finding.result is not None
    assert finding.stencil.base == 3 and finding.stencil.runs == (6, 7)


# ------------------------------------------------------------------ a real campaign's report
BUDGET = 6
DRAWS = 6
CAMPAIGN = "ident-lm"


@pytest.fixture(scope="module")
def lm_campaign(tmp_path_factory, small_case, prefect_api):
    """A real 6-call least-squares campaign on the small synthetic case: the box's centre and
    its forward-difference runs, so that its best call has a Jacobian at it or one step away;
    then 6 parameter sets drawn from the posterior there and simulated, apart from the
    budget."""
    root = tmp_path_factory.mktemp("ident")
    store = root / "store"
    run = subprocess.run([sys.executable, "-m", "hmflow.cli", "run", "--case", str(small_case),
                          "--budget", str(BUDGET), "--agent", "lm", "--workers", "2",
                          "--forecast-draws", str(DRAWS),
                          "--campaign", CAMPAIGN, "--storage", str(store)], cwd=root,
                         env=cli_env(prefect_api), capture_output=True, text=True, timeout=900, check=False)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return store


@pytest.mark.opm
def test_the_report_gives_the_posterior_of_a_least_squares_campaign(lm_campaign, small_case):
    """report.json's standard deviations are those of (J^T J)^-1 with J recomputed here from
    the journal with the campaign's own objective (the case's noise, refined from the calls the
    stored noise says); report.md and report.html print them, with the truth inside or not."""
    from hmcore.calibration.objective import Objective
    from hmcore.cases import load_case
    from storage import ArtifactStore, EvaluationJournal

    store = ArtifactStore(lm_campaign)
    rep = store.latest(CAMPAIGN, "report")
    doc = json.loads(rep.file("report.json").read_text())["identifiability"]
    assert doc["computed"] and doc["residuals"] == "whitened"
    assert doc["scaled_by_residual_variance"] is False
    rows = {r["index"]: r for r in EvaluationJournal(store, CAMPAIGN).rows()}
    assert doc["best_call"] == json.loads(rep.file("report.json").read_text())["best"]["index"] + 1

    case = load_case(str(small_case))
    objective = Objective.of_case(case)
    for v in store.versions(CAMPAIGN, "noise"):  # the refinements, in order
        objective = objective.refined(rows[v.read_json("noise.json")["refined_from_call"]])
    r0 = objective.residuals(rows[doc["jacobian_base_call"] - 1])[:-1]  # no penalty entry
    runs = [objective.residuals(rows[j - 1])[:-1] for j in doc["jacobian_runs"]]
    J = np.column_stack([(r - r0) / h for r, h in zip(runs, doc["steps_scaled"])])
    sd_scaled = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    half = np.array([(p.high - p.low) / 2 for p in case.space.parameters])
    got = {p["name"]: p for p in doc["parameters"]}
    for k, p in enumerate(case.space.parameters):
        assert not p.log
        assert got[p.name]["sd"] == pytest.approx(sd_scaled[k] * half[k], rel=1e-6)
    assert doc["chi2"] == pytest.approx(float(r0 @ r0), rel=1e-9)
    assert doc["chi2"] / doc["n"] == pytest.approx(
        objective.likelihood(rows[doc["jacobian_base_call"] - 1]), rel=1e-9)

    markdown = rep.file("report.md").read_text()
    html = rep.file("report.html").read_text()
    section = markdown[markdown.index("## Identifiability: what the data pin down"):]
    assert '<section id="identifiability">' in html and 'href="#identifiability"' in html
    truth = {p["name"]: p for p in doc["parameters"] if p["truth_inside"] is not None}
    assert len(truth) == len(case.space.parameters)  # the small case knows its truth
    for name, p in got.items():
        line = re.search(rf"^\| {name} \| [^\n]*$", section, re.MULTILINE)[0]
        assert f"| {p['sd']:.4g} |" in line and f"[{p['low']:.4g}, {p['high']:.4g}]" in line
        assert line.endswith("| yes |" if p["truth_inside"] else "| NO |")
        assert f"<td>{p['sd']:.4g}</td>" in html
    inside = sum(p["truth_inside"] for p in got.values())
    assert f"The known truth lies inside {inside} of {len(got)} 95 % intervals." in section
    if doc["chi2_per_dof"] > 2.25:  # the box's centre fits far worse than the noise
        assert "read the intervals as too narrow" in section
    for pair in doc["pairs"]:
        assert abs(pair["correlation"]) > PAIR_CORRELATION
        assert f"{pair['a']} and {pair['b']} trade off" in section

    # the same report from a journal without the finite-difference runs: says why and how
    from hmcore.reporting.report import build_report

    results = store.latest(CAMPAIGN, "results")
    case_doc = store.latest(CAMPAIGN, "case").read_json("case.json")
    best_doc = store.latest(CAMPAIGN, "best").read_json("metrics.json")
    alone = [r for r in results.read_json("records.json")["records"]
             if r["index"] == best_doc["index"]]
    finding = assess(alone, case_doc["parameters"], best_doc["index"], None, agent="lm")
    markdown, report_doc = build_report(CAMPAIGN, case_doc,
                                        results.read_parquet("evaluations.parquet"), best_doc,
                                        None, identifiability=finding)
    assert report_doc["identifiability"]["computed"] is False
    section = markdown[markdown.index("## Identifiability: what the data pin down"):]
    assert section.split("\n")[2].startswith("Not computed. Identifiability needs the Jacobian")
    assert f"`hmflow run --case {small_case} --agent lm`" in section
    assert "| poro_mult |" not in section.split("## Which responses")[0]


@pytest.mark.opm
def test_the_tables_command_prints_the_same_identifiability(lm_campaign, tmp_path, prefect_api):
    """``hmflow tables`` (the best case) prints the report's table and sentences, and writes
    them to its Markdown."""
    from storage import ArtifactStore

    doc = json.loads(ArtifactStore(lm_campaign).latest(CAMPAIGN, "report").file(
        "report.json").read_text())["identifiability"]
    out = tmp_path / "tables.md"
    run = subprocess.run([sys.executable, "-m", "hmflow.cli", "tables", "--storage",
                          str(lm_campaign), "--campaign", CAMPAIGN, "--markdown", str(out)],
                         capture_output=True, text=True, timeout=300, check=False,
                         env=cli_env(prefect_api, COLUMNS="200"))
    assert run.returncode == 0, run.stderr[-2000:]
    assert f"Identifiability at the best call (call {doc['best_call']})" in run.stdout
    for p in doc["parameters"]:
        assert re.search(rf"{p['name']}\s+│[^\n]*{p['sd']:.4g}", run.stdout)
    for name in doc["uninformed"]:
        assert f"{name}: the data do not inform it" in run.stdout
    text = out.read_text()
    assert "## Identifiability: what the data pin down" in text
    assert all(f"| {p['name']} |" in text for p in doc["parameters"])


@pytest.mark.opm
def test_the_forecast_is_made_of_runs_drawn_from_the_posterior_apart_from_the_budget(
        lm_campaign, small_case, prefect_api):
    """The draws stand on the report's posterior (its best call), lie in the box, are
    simulated into a journal of their own (the budget's journal keeps its 6 calls), and their
    valid runs are the forecast's members, which the page names; the same command again
    simulates nothing."""
    from hmcore.cases import load_case
    from storage import ArtifactStore, EvaluationJournal
    from storage.posterior import journal_name

    store = ArtifactStore(lm_campaign)
    ident = json.loads(store.latest(CAMPAIGN, "report").file("report.json").read_text())[
        "identifiability"]
    posterior = store.latest(CAMPAIGN, "posterior")
    drawn = posterior.read_json("draws.json")
    assert drawn["best_call"] == ident["best_call"] and drawn["kept"] == DRAWS, drawn
    space = load_case(str(small_case)).space
    for draw in drawn["draws"]:
        u = np.asarray(draw["action"])
        assert np.all(np.abs(u) <= 1.0)
        assert space.to_values(u) == pytest.approx(draw["values"])
    assert len(EvaluationJournal(store, CAMPAIGN).indices()) == BUDGET  # draws apart
    runs = EvaluationJournal(store, CAMPAIGN, journal_name(posterior.version)).rows()
    assert [r["action"] for r in runs] == [d["action"] for d in drawn["draws"]]
    valid = [r["index"] + 1 for r in runs if r["status"] == "COMPLETE"]
    curves = store.latest(CAMPAIGN, "curves")
    forecast = curves.read_json("forecast.json")
    if len(valid) >= 2:
        assert forecast["kind"] == "laplace" and forecast["member_draws"] == valid
        table = curves.read_parquet("forecast.parquet")
        assert set(table.members) == {len(valid)}
        html = store.latest(CAMPAIGN, "report").file("report.html").read_text()
        assert (f"{DRAWS} parameter sets drawn from the Laplace posterior at call "
                f"{drawn['best_call']}") in " ".join(html.split())
    else:  # (a box where the physics checks refuse nearly every draw: the best calls)
        assert forecast["kind"] == "near_best"

    stamps = {p.name: p.stat().st_mtime_ns for p in (lm_campaign / CAMPAIGN).glob(
        "evaluations*/*.json")}
    again = subprocess.run([sys.executable, "-m", "hmflow.cli", "run", "--case",
                            str(small_case), "--budget", str(BUDGET), "--agent", "lm",
                            "--workers", "2", "--forecast-draws", str(DRAWS), "--campaign",
                            CAMPAIGN, "--storage", str(lm_campaign)],
                           env=cli_env(prefect_api), capture_output=True, text=True,
                           timeout=900, check=False)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert store.latest(CAMPAIGN, "posterior").version == posterior.version
    assert {p.name: p.stat().st_mtime_ns for p in (lm_campaign / CAMPAIGN).glob(
        "evaluations*/*.json")} == stamps  # nothing simulated or journaled again


@pytest.mark.opm
def test_a_method_without_a_jacobian_gets_one_after_the_fit_for_its_posterior(
        tmp_path, small_case, prefect_api):
    """CMA-ES leaves no finite-difference stencil: one run per parameter is made at its best
    call after the fit, apart from the budget, and the report's posterior and the draws stand
    on it."""
    from hmcore.reporting.identifiability import jacobian_journal
    from storage import ArtifactStore, EvaluationJournal
    from tasks.posterior import STEP

    store_root = tmp_path / "store"
    run = subprocess.run([sys.executable, "-m", "hmflow.cli", "run", "--case", str(small_case),
                          "--budget", "3", "--agent", "cmaes", "--workers", "2",
                          "--forecast-draws", "2", "--campaign", "ident-cmaes", "--storage",
                          str(store_root)], cwd=tmp_path, env=cli_env(prefect_api),
                         capture_output=True, text=True, timeout=900, check=False)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    store = ArtifactStore(store_root)
    doc = json.loads(store.latest("ident-cmaes", "report").file("report.json").read_text())
    ident, best = doc["identifiability"], doc["best"]["index"]
    assert len(EvaluationJournal(store, "ident-cmaes").indices()) == 3  # the budget's calls
    runs = EvaluationJournal(store, "ident-cmaes", jacobian_journal(best)).rows()
    base = np.asarray(EvaluationJournal(store, "ident-cmaes").get(best)["action"])
    assert len(runs) == len(base)  # one per parameter
    for k, r in enumerate(runs):
        step = np.asarray(r["action"]) - base
        assert np.count_nonzero(np.abs(step) > 1e-12) == 1 and abs(step[k]) == pytest.approx(
            STEP)
    assert ident["computed"] and ident["jacobian_base_call"] == best + 1
    assert ident["jacobian_run_labels"] == [f"J-run {k + 1}" for k in range(len(base))]
    drawn = store.latest("ident-cmaes", "posterior").read_json("draws.json")
    assert drawn["best_call"] == best + 1 and drawn["kept"] == 2
