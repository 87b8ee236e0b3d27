"""The explanations' evidence and weights (hmcore.diagnosis.evidence) and what would separate
them (hmcore.diagnosis.separation): fake data, no simulator."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmcore.diagnosis.evidence import (AnswerKind, EvidenceMethod, Fit, jtj_eigenvalues,
                                       log_occam, rank, softmax)
from hmcore.diagnosis.separation import LINE, separations, tabulate


def fit(id_, ssr, eig=(), ho=0.0, n_bic=0, kind="x", log_prior=0.0):
    return Fit(id_, kind, float(ssr), float(ho), np.asarray(eig, float), n_bic, log_prior)


# ----------------------------------------------------------------------------- evidence
def _linear_fits(rng, n, effect):
    """Data y = 1 + effect * x + noise; 'none' fits a constant, 'slope' a constant and slope;
    Jacobians in scaled coordinates (each parameter's range [-1, 1] is [-5, 5])."""
    x = np.linspace(-1, 1, n)
    y = 1.0 + effect * x + rng.standard_normal(n)
    X0, X1 = np.ones((n, 1)), np.column_stack([np.ones(n), x])
    out = []
    for name, X in (("none", X0), ("slope", X1)):
        beta, *_ = np.linalg.lstsq(X, y, rcond=None)
        r = y - X @ beta
        out.append(fit(name, r @ r, jtj_eigenvalues(5.0 * X)))
    return out


def test_occam_prefers_the_smaller_model_when_the_extra_parameter_is_noise():
    """Nested linear models, the extra slope absent: the evidence names `none` on most seeds
    (the SSR drop of a noise parameter is chi2(1), the Occam cost ~ 1/2 log n); with a real
    slope it names the slope, alone."""
    n = 400
    picks = [rank(_linear_fits(np.random.default_rng(seed), n, 0.0), n).items[0].fit.id
             for seed in range(40)]
    assert picks.count("none") >= 34, picks
    for seed in range(5):
        r = rank(_linear_fits(np.random.default_rng(seed), n, 1.0), n)
        assert r.members == ("slope",) and r.kind is AnswerKind.SINGLE


def test_laplace_matches_the_exact_linear_gaussian_evidence():
    """For a linear model with the Gaussian prior whose height the module uses (variance
    w^2/2pi, centred at u = 0), the exact log evidence (relative to the model without the
    parameter) is the module's Laplace one less that prior's pull on the estimate,
    ``u^2 / (2 var)``, which the uniform prior the module stands for does not have (at most
    pi/4 nats inside the range)."""
    rng = np.random.default_rng(7)
    n = 300
    x = np.linspace(-1, 1, n)
    var = 2.0 ** 2 / (2 * math.pi)

    def exact(X, y):
        C = np.eye(n) + var * X @ X.T
        return -0.5 * np.linalg.slogdet(C)[1] - 0.5 * y @ np.linalg.solve(C, y)

    for slope in (0.0, 0.3, 1.0):
        y = slope * x + rng.standard_normal(n)
        X1 = (2.0 * x)[:, None]  # scaled coordinate u in [-1, 1] spans slopes [-2, 2]
        u, *_ = np.linalg.lstsq(X1, y, rcond=None)
        r = y - X1 @ u
        laplace = -0.5 * (r @ r) + log_occam(jtj_eigenvalues(X1)) - (-0.5 * y @ y)
        truth = exact(X1, y) - exact(np.zeros((n, 0)), y)
        assert laplace - u[0] ** 2 / (2 * var) == pytest.approx(truth, abs=0.02)
        assert 0.0 <= laplace - truth <= math.pi / 4 + 0.02


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 500), st.floats(0, 100), st.integers(0, 3)),
                min_size=1, max_size=8),
       st.floats(0.5, 0.99))
def test_weights_and_the_answer_set(rows, mass):
    fits = [fit(f"c{i}", s, [1e3] * k, ho) for i, (s, ho, k) in enumerate(rows)]
    r = rank(fits, 200, mass=mass)
    w = np.array([x.weight for x in r.items])
    assert np.all(w >= 0) and w.sum() == pytest.approx(1.0)
    assert list(w) == sorted(w, reverse=True)
    k = len(r.members)
    assert list(r.members) == [x.fit.id for x in r.items[:k]]
    assert w[:k].sum() >= mass - 1e-9 or k == len(fits)
    assert k == 1 or w[:k - 1].sum() < mass  # the smallest such set
    assert (r.kind is AnswerKind.SINGLE) == (k == 1)
    # the order does not depend on the order the fits were given in
    again = rank(list(reversed(fits)), 200, mass=mass)
    assert again.weights == pytest.approx(r.weights)


@given(st.floats(0, 1e4), st.floats(1e-3, 1e6), st.integers(0, 4))
def test_a_parameter_the_data_constrain_costs_evidence(ssr, lam, extra):
    """Same fit, one more constrained parameter: lower evidence (Occam); a parameter the data
    do not constrain (eigenvalue 0) costs nothing."""
    base = [lam] * extra
    r = rank([fit("small", ssr, base), fit("big", ssr, base + [lam])], 100)
    assert r.items[0].fit.id == "small"
    free = rank([fit("small", ssr, base), fit("free", ssr, base + [0.0])], 100)
    assert free.items[0].log_evidence == pytest.approx(free.items[1].log_evidence)


def test_heldout_history_and_failures_and_bic():
    """The held-back SSR moves weight; a failed fit weighs 0; parameters without a Jacobian
    pay 1/2 log n each."""
    r = rank([fit("a", 100, [50.0], ho=10), fit("b", 100, [50.0], ho=30)], 100)
    assert r.members == ("a",) and r.bayes_factor == pytest.approx(math.exp(10.0))
    assert rank([fit("a", 100, [50.0], ho=10), fit("b", 100, [50.0], ho=30)], 100,
                heldout=False).kind is AnswerKind.SET
    r = rank([fit("a", 100), fit("dead", math.inf, [1.0])], 100)
    assert r.weights["dead"] == 0.0
    b = fit("u", 100, [], n_bic=2)
    assert b.method is EvidenceMethod.BIC and b.n_parameters == 2
    r = rank([fit("none", 100), b], 400)
    assert r.items[1].log_occam == pytest.approx(-math.log(400))


def test_an_inflated_noise_model_is_read_less_sharply():
    """When the best fit leaves 3x the noise, SSR differences count a third: a gap that is
    decisive under the noise model becomes a set."""
    n = 100
    tight = rank([fit("a", 100), fit("b", 106)], n)
    loose = rank([fit("a", 300), fit("b", 306)], n)
    assert tight.scale == 1.0 and tight.kind is AnswerKind.SINGLE
    assert loose.scale == pytest.approx(3.0) and loose.kind is AnswerKind.SET


def test_softmax_is_stable():
    w = softmax(np.array([-1e6, -1e6 + 1.0, -np.inf]))
    assert w[2] == 0.0 and w[1] / w[0] == pytest.approx(math.e)
    assert list(softmax(np.array([-np.inf, -np.inf]))) == [0.5, 0.5]


# ----------------------------------------------------------------------------- separation
@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2), st.integers(0, 29), st.floats(0.1, 20), st.floats(0.01, 3))
def test_the_largest_difference_in_sigma_is_found(s_peak, t_peak, size, sig):
    """Three models on three series: B differs from A by a bump of ``size`` sigma at
    (s_peak, t_peak); C equals A. The A-B pair names that series and day."""
    rng = np.random.default_rng(0)
    days = np.arange(30) * 100.0
    base = rng.uniform(10, 20, (3, 30))
    sigma = np.array([sig, 2 * sig, 3 * sig])
    b = base.copy()
    b[s_peak] += size * sigma[s_peak] * np.exp(-0.5 * ((np.arange(30) - t_peak) / 2.0) ** 2)
    preds = np.stack([base, b, base])
    series = [("P1", "WBHP"), ("P1", "WWCT"), ("P2", "WOPR")]
    out = separations(["A", "B", "C"], series, days, preds, sigma)
    ab = next(s for s in out if (s.a, s.b) == ("A", "B"))
    ac = next(s for s in out if (s.a, s.b) == ("A", "C"))
    assert (ab.well, ab.quantity) == series[s_peak] and ab.day == days[t_peak]
    assert ab.z == pytest.approx(size)
    assert ac.z == 0.0 and ac.from_day is None
    if size >= LINE:
        assert ab.from_day is not None and ab.from_day <= ab.day
        assert abs(b[s_peak] - base[s_peak])[days == ab.from_day][0] >= LINE * sigma[s_peak]
    else:
        assert ab.from_day is None


def test_the_sentence_and_the_grid():
    frames = {
        "krw": pd.DataFrame({"well": "PRO-11", "quantity": "WWCT",
                             "days": [0.0, 1000, 2000, 3000, 4000],
                             "value": [0.0, 0.1, 0.2, 0.3, 0.4]}),
        "contact": pd.DataFrame({"well": "PRO-11", "quantity": "WWCT",
                                 "days": [0.0, 2000, 4000], "value": [0.0, 0.2, 0.8]}),
    }
    ids, series, days, preds, sigma = tabulate(frames, {("PRO-11", "WWCT"): 0.1})
    assert series == [("PRO-11", "WWCT")] and preds.shape == (2, 1, 5)
    assert preds[1, 0, 3] == pytest.approx(0.5)  # interpolated at day 3000
    (s,) = separations(ids, series, days, preds, sigma)
    assert s.day == 4000 and s.z == pytest.approx(4.0) and s.from_day == 3000
    text = s.sentence(history_end=2500)
    assert text.startswith("a water-cut measurement at PRO-11 after day 3000 separates krw "
                           "from contact by 4.0 sigma")
    assert "inside" not in text
    assert "inside the fitted history" in s.sentence(history_end=3500)
    # two models never 2 sigma apart: no single measurement separates them, says the sentence
    near = preds.copy()
    near[1] = preds[0] + 0.15  # contact = krw + 1.5 sigma everywhere
    (c,) = separations(ids, series, days, near, sigma)
    assert c.from_day is None and c.z == pytest.approx(1.5)
    assert c.sentence().startswith("no single measurement separates krw from contact by 2 "
                                   "sigma in the schedule run; the most, 1.5 sigma: a "
                                   "water-cut measurement at PRO-11")
    # a series with no sigma is left out
    assert tabulate(frames, {})[1] == []


# ----------------------------------------------------------------------------- the judge
@pytest.fixture(scope="module")
def synthetic_candidates(tmp_path_factory):
    pytest.importorskip("opm.io")
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.model.parameters import ParameterSpace
    from hmcore.scenarios.hidden import synthetic_deck_info
    from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH

    info = synthetic_deck_info(0, tmp_path_factory.mktemp("deck"))
    return {c.id: c for c in build_candidates(info, ParameterSpace.reference(),
                                              dict(SYNTHETIC_TRUTH))}


def _judged_doc(members, ranked, kind=None):
    """A diagnosis document whose answer is ``members`` (single when one), its causes the
    candidates ``ranked`` (then none)."""
    causes = [{"id": c.id, "kind": c.kind, "wells": list(c.wells), "layers": list(c.layers),
               "chi2": 40.0, "machine": c.machine()} for c in ranked]
    causes.append({"id": "none", "kind": "none", "wells": [], "layers": [], "chi2": 15.0})
    doc = {"causes": causes, "accepted": [], "selected": None, "verdict": "",
           "gain": {"fit_before": 0.03, "fit_after": 0.03, "heldout_before": 0.02,
                    "heldout_after": 0.02, "ssr_heldout_before": 1.0,
                    "ssr_heldout_after": 1.0}}
    if members is not None:
        doc["answer"] = {"kind": kind or ("single" if len(members) == 1 else "set"),
                         "members": list(members)}
    return doc


def test_the_judge_counts_right_honest_and_wrong_with_set_sizes(synthetic_candidates):
    from hmcore.scenarios.effects import HiddenEffect
    from hmcore.scenarios.judge import answer_outcome, judge

    c = synthetic_candidates
    skin, krw = c["well_skin:PROD3"], c["relative_permeability:water"]
    other = next(v for k, v in c.items() if k.startswith("layer_permeability"))
    truth = [HiddenEffect(skin, 12.0)]
    ranked = [krw, skin, other]

    def outcome(members, effects=truth):
        return answer_outcome(_judged_doc(members, ranked), effects)

    assert outcome([skin.id]) == {"outcome": "right", "set_size": 1, "members": [skin.id]}
    assert outcome([krw.id, skin.id])["outcome"] == "honest"
    assert outcome([krw.id, skin.id])["set_size"] == 2
    assert outcome([krw.id, other.id])["outcome"] == "wrong"
    assert outcome([krw.id])["outcome"] == "wrong"  # a confident wrong name
    assert outcome(["none"], [])["outcome"] == "right"  # the control
    assert outcome(["none", krw.id], [])["outcome"] == "honest"
    assert outcome([krw.id], [])["outcome"] == "wrong"
    # two effects: a pair of round 2 that names both ("a+b")
    pair = [HiddenEffect(skin, 12.0), HiddenEffect(krw, 2.0)]
    assert outcome([f"{krw.id}+{skin.id}"], pair)["outcome"] == "right"
    assert outcome([skin.id, f"{skin.id}+{krw.id}"], pair)["outcome"] == "honest"
    assert outcome([skin.id], pair)["outcome"] == "wrong"
    assert outcome([f"{skin.id}+{other.id}"], pair)["outcome"] == "wrong"
    # judge() carries it beside its own verdict
    j = judge(_judged_doc([krw.id, skin.id], ranked), truth[0])
    assert j["outcome"] == "honest" and j["set_size"] == 2 and not j["found"]


def test_a_diagnosis_stored_before_the_evidence_is_judged_as_it_was(synthetic_candidates):
    """An older diagnosis.json has no answer: it is upgraded (one home of format upgrades)
    to its first cause, derived, and judged right exactly when it was found."""
    from hmcore.scenarios.effects import HiddenEffect
    from hmcore.scenarios.judge import judge
    from hmcore.scoring.record_format import upgrade_diagnosis

    skin = synthetic_candidates["well_skin:PROD3"]
    old = _judged_doc(None, [skin])
    up = upgrade_diagnosis(old)
    assert "answer" not in old and up["answer"]["derived"] and \
        up["answer"]["members"] == [skin.id]
    assert upgrade_diagnosis(up) is up
    j = judge(old, HiddenEffect(skin, 12.0))  # ranked first, but not selected: not found
    assert not j["found"] and j["outcome"] == "wrong" and j["set_size"] == 1
    found = {**old, "selected": {"id": skin.id}, "gain": {**old["gain"], "heldout_after": 0.01}}
    assert judge(found, HiddenEffect(skin, 12.0))["outcome"] == "right"


# ----------------------------------------------------------------------------- the answer
def _run(wct_end):
    """A run whose water cut at PRO-11 rises linearly to ``wct_end`` at day 4000."""
    from types import SimpleNamespace

    from hmcore.diagnosis.runs import Run

    days = np.arange(0.0, 4001.0, 500.0)
    frame = pd.DataFrame({"well": "PRO-11", "quantity": "WWCT", "days": days,
                          "value": wct_end * days / days[-1]})
    return Run({}, SimpleNamespace(responses=frame), np.zeros(3), np.zeros(2))


def test_an_ambiguous_answer_names_the_measurement_that_separates_it():
    """Two explanations that fit alike (same SSRs and curvature) form a set; the answer says
    which measurement separates them, from their runs; a third far worse one is left out."""
    from types import SimpleNamespace

    from hmcore.diagnosis.answer import section, with_pair

    obs = SimpleNamespace(rows=pd.DataFrame({"well": ["PRO-11"] * 3, "quantity": "WWCT",
                                             "sigma": [0.05, 0.05, np.nan]}),
                          history_end_days=2000.0)
    fits = [fit("contact", 300, [400.0] * 6), fit("krw", 300.5, [400.0] * 6),
            fit("none", 360, [400.0] * 5)]
    runs = {"contact": _run(0.8), "krw": _run(0.4), "none": _run(0.3)}
    a = section(fits, 300, runs, obs)
    assert a["kind"] == "set" and a["members"] == ["contact", "krw"]
    (sep,) = a["separations"]
    assert (sep["well"], sep["quantity"], sep["day"]) == ("PRO-11", "WWCT", 4000.0)
    assert sep["z"] == pytest.approx(0.4 / 0.05)
    assert sep["from_day"] == 1000.0  # the difference 0.4 * day / 4000 reaches 2 sigma (0.1)
    assert "cannot separate contact" in a["text"] and "water-cut measurement at PRO-11" \
        in a["text"] and "8.0 sigma" in a["text"]
    w = {x["id"]: x["weight"] for x in a["explanations"]}
    assert w["none"] < 1e-6 and sum(w.values()) == pytest.approx(1.0)
    # round 2's pair fits far better: it takes the weight alone
    again = with_pair(a, fit("contact+krw", 250, [400.0] * 7, kind="pair"))
    assert again["kind"] == "single" and again["members"] == ["contact+krw"]
    assert again["separations"] == []
    # a single answer: no separation is looked for
    one = section(fits[:1] + fits[2:], 300, runs, obs)
    assert one["kind"] == "single" and one["separations"] == []


def test_reveal_prints_the_answer_by_the_evidence(tmp_path):
    """`hmflow reveal` says right / honest / wrong and the answer's set beside FOUND."""
    import json

    from typer.testing import CliRunner

    from hmflow.cli import app

    control = tmp_path / "hidden_effect.json"
    control.write_text(json.dumps({"effect": None, "truth": {}}))
    doc = _judged_doc(["none", "unexplained"], [])
    doc["causes"][0]["description"] = "nothing beyond noise"
    path = tmp_path / "diagnosis.json"
    path.write_text(json.dumps(doc))
    out = CliRunner().invoke(app, ["reveal", "--hidden", str(control), "--diagnosis", str(path)])
    assert out.exit_code == 0, out.output  # found: the control's none, selected nothing
    assert "by the evidence: HONEST (answer of 2: none, unexplained)" in out.output
