"""Unit tests of the diagnosis (fast, no simulator): noise estimation, whitened residuals,
residual statistics, the score test on linear data, the bounded LM, the extension library on
PUNQ-S3's and the synthetic deck, and the whole orchestration on a linear stand-in simulator."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from hmcore.diagnosis.attribution import projector_basis, score_test
from hmcore.diagnosis.recalibrate import (Coordinates, LevenbergMarquardt, LMSettings,
                                          run_lockstep)
from hmcore.scoring.observations import ObservationSet
from hmcore.diagnosis.residuals import analyse_residuals
from hmcore.scoring.noise import estimate_noise, robust_variogram
from hmcore.model.parameters import Parameter, ParameterSpace

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
needs_punq = pytest.mark.skipif(not (PUNQ / "PUNQS3.DATA").is_file(),
                                reason=f"PUNQ-S3 data not found at {PUNQ}")


def ar1(rng, n, rho):
    z = np.empty(n)
    z[0] = rng.standard_normal()
    for t in range(1, n):
        z[t] = rho * z[t - 1] + math.sqrt(1 - rho * rho) * rng.standard_normal()
    return z


# ============================================================================ noise
@pytest.mark.parametrize("rho", [0.0, 0.5, 0.7])
def test_noise_level_and_correlation_are_recovered_from_noisy_series(rho):
    rng = np.random.default_rng(3)
    sig = [2.0, 3.0, 5.0] * 4
    series = []
    for s in sig:
        t = np.linspace(0, 1, 90)
        trend = 20 * t + 5 * np.sin(3 * t)  # a smooth signal: not noise
        series.append(trend + s * ar1(rng, t.size, rho))
    est, r = estimate_noise(series)
    assert abs(r - rho) < 0.15
    for s, e in zip(sig, est):
        assert 0.7 * s < e < 1.35 * s


def test_variogram_ignores_linear_trends_and_single_jumps():
    x = np.arange(50, dtype=float) * 10.0
    x[25:] += 500.0
    g = robust_variogram(x, 2)
    assert np.allclose(g, 0.0)
    assert np.isnan(robust_variogram(np.ones(3), 2)).all()


def _observed(rng, wells=("W1", "W2"), n=60, bias=None, rho=0.7, sigma=True):
    """Observed BHP/WCT/GOR/WOPR rows with AR(1) noise around a known truth."""
    rows, truth = [], []
    days = np.arange(1, n + 1) * 30.0
    for w in wells:
        bhp = 200 - 0.02 * days
        wct = np.clip((days - 900) / 1500, 0, 0.8)
        gor = 100 + 0.03 * days
        for q, v, s in (("WBHP", bhp, 3.0), ("WWCT", wct, 0.02), ("WGOR", gor, 0.1 * gor),
                        ("WOPR", np.full(n, 100.0), np.nan)):
            noise = 0.0 if q == "WOPR" else s * ar1(rng, n, rho)
            rows.append(pd.DataFrame({"well": w, "days": days, "quantity": q,
                                      "value": v + noise, "sigma": s if sigma else np.nan,
                                      "flowing": True, "derived": False}))
            tv = v + (bias if (bias and q == "WBHP" and w == wells[0]) else 0.0)
            truth.append(pd.DataFrame({"well": w, "days": days, "quantity": q, "value": tv}))
    return pd.concat(rows, ignore_index=True), pd.concat(truth, ignore_index=True)


def test_whitened_residuals_of_pure_noise_are_unit_white():
    rng = np.random.default_rng(0)
    obs, sim = _observed(rng, wells=[f"W{i}" for i in range(8)], n=120)
    o = ObservationSet.from_observed(obs, 2500.0).refine(sim, obs)
    assert abs(o.rho["WBHP"] - 0.7) < 0.15
    r = o.residual_vector(sim, "fit")
    assert r.size == o.n_fit
    q = o.rows.quantity.to_numpy()[o.vector_index("fit")]
    assert np.all(r[q == "WOPR"] == 0)  # the rate control is matched exactly
    assert 0.75 < float(np.mean(r[q != "WOPR"] ** 2)) < 1.25
    e = r[q == "WBHP"]
    assert abs(np.corrcoef(e[1:], e[:-1])[0, 1]) < 0.15  # the AR(1) correlation is gone


def test_sigma_is_estimated_from_residuals_when_not_given():
    rng = np.random.default_rng(1)
    obs, sim = _observed(rng, wells=[f"W{i}" for i in range(6)], n=100, sigma=False)
    o = ObservationSet.from_observed(obs, 2500.0).refine(sim, obs)
    bhp = o.rows[o.rows.quantity == "WBHP"]
    assert set(bhp.sigma_source) == {"estimated"}
    assert 2.0 < bhp.sigma.median() < 4.2  # true 3 bar
    gor = o.rows[o.rows.quantity == "WGOR"]
    assert 0.06 < float((gor.sigma / gor.observed).median()) < 0.15  # true 10 %
    oil = o.rows[o.rows.quantity == "WOPR"]
    assert set(oil.sigma_source) == {"rate"} and np.allclose(oil.sigma, 5.0)


def test_residual_analysis_flags_a_bias_beyond_noise_and_not_noise():
    rng = np.random.default_rng(2)
    obs, sim = _observed(rng, n=80, bias=6.0)
    o = ObservationSet.from_observed(obs, 1800.0).refine(sim, obs)
    res = analyse_residuals(o, sim)
    json.dumps(res)  # serialisable
    w1 = res["wells"]["W1"]["bhp"]
    assert w1["fit"]["beyond_noise"] and w1["fit"]["z_bias"] > 3
    assert w1["fit"]["bias"] == pytest.approx(6.0, abs=2.0)
    assert set(w1) >= {"fit", "early", "late", "heldout", "flowing"}
    assert not res["wells"]["W2"]["bhp"]["fit"]["beyond_noise"]
    assert any(f["well"] == "W1" and f["response"] == "bhp" for f in res["flags"])
    assert res["summary"]["n_fit"] == o.n_fit


def test_breakthrough_timing_error_is_measured():
    rng = np.random.default_rng(4)
    obs, sim = _observed(rng, n=80)
    late = sim.copy()
    m = late.quantity == "WWCT"
    late.loc[m, "value"] = np.clip((late.loc[m, "days"] - 1200) / 1500, 0, 0.8)
    o = ObservationSet.from_observed(obs, 2400.0)
    bt = analyse_residuals(o, late)["breakthrough"]["W1"]["water"]
    assert bt["error_days"] == pytest.approx(300, abs=90) and bt["beyond_noise"]


# ============================================================================ score test
def test_score_test_finds_the_direction_that_made_the_residual():
    rng = np.random.default_rng(5)
    n = 400
    g = rng.standard_normal((n, 3))  # global parameters' sensitivities
    j_true = rng.standard_normal(n)
    j_other = rng.standard_normal(n)
    g_part = g @ np.array([1.0, -0.5, 0.2])
    j_mimic = g_part + 0.05 * rng.standard_normal(n)
    r = 0.4 * j_true + rng.standard_normal(n)
    Q = projector_basis(g)
    s_true = score_test(r, j_true, Q)
    s_other = score_test(r, j_other, Q)
    # a misfit the globals can fix is no evidence for a candidate that resembles them
    s_mimic = score_test(r + 3 * g_part, j_mimic, Q)
    assert score_test(r + 3 * g_part, j_mimic).chi2 > 100  # it would score without the refit
    assert s_true.chi2 > 30 and s_true.score > 0.1
    assert s_other.chi2 < 10 and s_mimic.chi2 < 10
    assert s_true.step_u == pytest.approx(-0.4, abs=0.1)
    # exact linear algebra: score = (j.r)^2 / (j.j r.r)
    s = score_test(r, j_true)
    assert s.score == pytest.approx((j_true @ r) ** 2 / ((j_true @ j_true) * (r @ r)))
    # a step outside the bounds is cut there, and a forbidden direction scores zero
    assert score_test(r, j_true, None, (-0.1, 1.0)).step_u == pytest.approx(-0.1)
    assert score_test(r, j_true, None, (0.0, 1.0)).chi2 == 0.0


def test_pure_noise_scores_like_chi_square_one():
    rng = np.random.default_rng(6)
    chi = [score_test(rng.standard_normal(300), rng.standard_normal(300)).chi2
           for _ in range(2000)]
    assert 0.9 < np.mean(chi) < 1.1
    assert np.quantile(chi, 0.999) < 15


# ============================================================================ LM
def test_coordinates_round_trip_and_log_scale():
    params = [Parameter(name="k", kind="multiply", keywords=("PERMX",), low=0.1, high=10.0),
              Parameter(name="s", kind="skin", low=-5, high=15)]
    c = Coordinates(params)
    u = c.to_u({"k": 1.0, "s": 5.0})
    assert np.allclose(u, [0.0, 0.0])
    assert c.to_values(np.array([1.0, -1.0])) == pytest.approx({"k": 10.0, "s": -5.0})
    assert c.to_values(np.array([0.5, 0.5]))["k"] == pytest.approx(10 ** 0.5)
    # a relative-permeability exponent is a factor (log); a critical-saturation shift is not:
    # it crosses 0 (and a case's own may start at 0)
    rel = Coordinates([Parameter(name="n", kind="relperm", keywords=("SWOF",), item=2,
                                 mode="power", low=0.4, high=3.0),
                       Parameter(name="d", kind="relperm", keywords=("SWOF",), item=2,
                                 mode="endpoint", low=-0.2, high=0.2),
                       Parameter(name="d0", kind="relperm", keywords=("SGOF",), item=2,
                                 mode="endpoint", low=0.0, high=0.1)])
    assert list(rel.log) == [True, False, False]
    u = rel.to_u({"n": 1.0, "d": 0.0, "d0": 0.0})
    assert np.all(np.isfinite(u)) and u[1] == pytest.approx(0.0) and u[2] == pytest.approx(-1.0)
    assert rel.to_values(np.array([0.0, 0.5, 0.0])) == pytest.approx(
        {"n": (0.4 * 3.0) ** 0.5, "d": 0.1, "d0": 0.05})


def _model(u):
    t = np.linspace(0, 1, 30)
    return np.exp(-2.0 * (u[0] + 1) * t) * (1 + 0.5 * u[1]) + 0.3 * u[2] * t


def test_bounded_lm_converges_on_a_nonlinear_problem_and_respects_bounds():
    u_true = np.array([0.3, -0.4, 0.6])
    data = _model(u_true)
    lm = LevenbergMarquardt(np.zeros(3), LMSettings(fd_step=0.01, max_iter=30, ftol=1e-10,
                                                    atol=0.0, max_evaluations=300))
    run_lockstep([lm], lambda batch: [(_model(u) - data, None) for _, u in batch])
    assert np.allclose(lm.best.u, u_true, atol=2e-3)
    # the optimum outside the box: the fit stops at the bound
    data2 = _model(np.array([0.3, -0.4, 2.0]))
    lm2 = LevenbergMarquardt(np.zeros(3), LMSettings(fd_step=0.01, max_iter=30, ftol=1e-10,
                                                     atol=0.0, max_evaluations=300))
    run_lockstep([lm2], lambda batch: [(_model(u) - data2, None) for _, u in batch])
    assert lm2.best.u[2] == pytest.approx(1.0) and np.all(np.abs(lm2.best.u) <= 1.0)


def test_lockstep_batches_every_minimiser_and_failed_runs_are_survived():
    data = _model(np.array([0.1, 0.2, -0.3]))
    batches = []

    def evaluate(batch):
        batches.append(len(batch))
        return [(None if abs(u[0] - 0.5) < 1e-9 else _model(u) - data, None) for _, u in batch]

    ms = [LevenbergMarquardt(np.zeros(3), LMSettings(fd_step=0.05)),
          LevenbergMarquardt(np.full(3, 0.5), LMSettings(fd_step=0.05))]
    run_lockstep(ms, evaluate)
    assert batches[0] == 8  # both start points and their finite differences at once
    assert ms[0].done and ms[0].best.ssr < 1e-3
    assert ms[1].done and ms[1].reason == "the start point failed to simulate"


# ============================================================================ extensions
@pytest.fixture(scope="module")
def punq_info():
    pytest.importorskip("opm.io")
    if not (PUNQ / "PUNQS3.DATA").is_file():
        pytest.skip(f"PUNQ-S3 data not found at {PUNQ}")
    from hmcore.eclipse.deck_info import DeckInfo

    return DeckInfo.inspect(PUNQ / "PUNQS3.DATA")


@needs_punq
def test_extension_library_for_punq(punq_info, tmp_path):
    from hmcore.model.run_deck import prepare_run_deck
    from hmcore.diagnosis.candidate import DEFAULT_KINDS, KINDS, extended_space
    from hmcore.diagnosis.extensions import build_candidates, dated_productivity

    space = ParameterSpace.reference()
    cands = build_candidates(punq_info, space, {"skin": 5.0})
    kinds = {c.kind for c in cands}
    assert kinds == set(DEFAULT_KINDS) - {"productivity_change"}  # dated by the ranking, below
    asked = build_candidates(punq_info, space, {}, KINDS)  # every family, when asked for
    assert {c.id for c in asked} - {c.id for c in cands} == {
        "contact_depth:woc", "contact_depth:goc", "solution_gas:rsvd"}
    assert {c.id for c in build_candidates(punq_info, space, {}, ("productivity_change",))} \
        == {f"well_skin:{w}" for w in punq_info.producers}  # the probes its date scan reads
    day = punq_info.report_days[30]
    cands.append(dated_productivity(punq_info, "PRO-4", day))
    assert cands[-1].parameter.start_day == day and cands[-1].details["start_date"] in \
        cands[-1].description
    by = {c.id: c for c in cands}
    nx, ny, nz = punq_info.dims
    assert {c.wells[0] for c in cands if c.kind == "well_skin"} == set(punq_info.producers)
    assert by["well_skin:PRO-1"].neutral == 5.0  # the calibrated global skin
    assert by["regional_permeability:PRO-1"].parameter.box == (7, 13, 19, 25, 1, nz)
    assert [c.layers for c in cands if c.kind == "layer_permeability"] == [(k,) for k in
                                                                         range(1, nz + 1)]
    assert by["layer_permeability:5"].wells == ("PRO-1", "PRO-4", "PRO-12")
    # the global PERMZ multiplier exists, so only per-layer vertical candidates
    assert [c.id for c in cands if c.kind == "vertical_permeability"] == \
        [f"vertical_permeability:{k}" for k in range(1, nz + 1)]
    aq = [c for c in cands if c.kind == "aquifer_strength"]
    assert [(c.parameter.keywords, c.parameter.item, c.parameter.match) for c in aq] == \
        [(("AQUCT",), 4, "1"), (("AQUCT",), 4, "2")]
    faults = [c for c in cands if c.kind == "fault_transmissibility"]
    assert {c.parameter.keywords[0] for c in faults} == {"MULTX", "MULTY"}
    for c in faults:  # a plane between two non-empty groups of wells, through all layers
        a, b = c.details["groups"]
        assert a and b and c.parameter.box[4:] == (1, nz)
    relperm = {(c.details["phase"], c.parameter.mode): c.parameter for c in cands
               if c.kind == "relative_permeability"}  # each curve's shape, level, start
    assert set(relperm) == {(ph, m) for ph in ("water", "gas")
                            for m in ("power", "scale", "endpoint")}
    assert by["relative_permeability:gas:endpoint"].neutral == 0.0  # a shift: 0 is none
    assert all(p.keywords == (("SWFN",) if ph == "water" else ("SGFN",)) and p.item == 2
               for (ph, _), p in relperm.items())
    for c in cands:
        assert c.description and c.parameter.low < c.neutral <= c.parameter.high or \
            c.parameter.low <= c.neutral <= c.parameter.high
        json.dumps(c.machine())
    # every candidate renders into a per-run deck (no simulation)
    ext = extended_space(space, cands)
    values = {c.name: c.probe for c in cands}
    deck = prepare_run_deck(PUNQ / "PUNQS3.DATA", values, ext, tmp_path / "deck", punq_info)
    text = deck.read_text()
    assert "'MULTX' 0.01 9 9 1 28 1 5 /" in text
    assert "'PERMX' 0.4 1 19 1 28 3 3 /" in text
    assert "41.25" in text  # AQUCT item 4 (137.5 mD) x 0.3
    assert f"productivity multipliers from day {day:g}" in text and "'PRO-4' 0.5 /" in text


def test_extension_library_for_the_synthetic_deck(tmp_path):
    pytest.importorskip("opm.io")
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.generators import draw_effect
    from hmcore.scenarios.hidden import synthetic_deck_info

    info = synthetic_deck_info(0, tmp_path)
    space = ParameterSpace.reference()
    cands = build_candidates(info, space, {"skin": 3.0})
    aq = {c.parameter.item: c for c in cands if c.kind == "aquifer_strength"}
    assert set(aq) == {4, 6} and aq[4].parameter.keywords == ("AQUFETP",)
    assert aq[4].parameter.match is None  # one aquifer
    tables = {c.parameter.keywords[0] for c in cands if c.kind == "relative_permeability"}
    assert tables == {"SWOF", "SGOF"}
    # a critical saturation moves down only as far as the table's first row: the synthetic
    # SWOF starts at its critical saturation (no room), its SGOF 0.05 above its first row;
    # that end is a limit, not an open end
    from hmcore.diagnosis.candidate import open_end
    from hmcore.diagnosis.extensions import critical_room
    from hmcore.model.deck_values import base_values

    by = {c.id: c for c in cands}
    water, gas = (by[f"relative_permeability:{ph}:endpoint"] for ph in ("water", "gas"))
    assert critical_room(info, "SWOF") == 0.0 and water.parameter.low == 0.0
    assert gas.parameter.low == pytest.approx(-critical_room(info, "SGOF")) == -0.05
    assert water.parameter.high == gas.parameter.high == 0.2
    assert open_end(gas, -0.05, 0.05) is None and open_end(gas, 0.2, 0.05) == "high"
    own = ParameterSpace(parameters=(*space.parameters, water.parameter))
    assert base_values(info, own)[water.name] == 0.0  # as given: no shift, not a factor of 1
    for seed in range(8):  # a drawn shift is a saturation change where the table has room
        e = draw_effect("relative_permeability", seed, info, space, {"skin": 3.0},
                        choices=[water.id, gas.id])
        assert 0.05 <= abs(e.value) <= 0.10 and e.value >= e.parameter.low
    # hidden effects are drawn deterministically per seed, inside the bounds
    for kind in ("well_skin", "fault_transmissibility", "aquifer_strength"):
        e1 = draw_effect(kind, 7, info, space, {"skin": 3.0})
        e2 = draw_effect(kind, 7, info, space, {"skin": 3.0})
        assert e1 == e2 and e1.kind == kind
        assert e1.parameter.low <= e1.value <= e1.parameter.high
    kinds_by_seed = {draw_effect("layer_permeability", s, info, space, {}).candidate.layers
                     for s in range(12)}
    assert len(kinds_by_seed) >= 3  # the seed varies the layer


# ============================================================================ orchestration
class LinearSimulator:
    """A stand-in simulator: every parameter adds a fixed random signature times its change
    from the neutral value (in scaled coordinates) to smooth base responses of four wells, so
    the diagnosis's job is exact linear algebra plus noise."""

    def __init__(self, hidden: Parameter | None = None, hidden_value: float = 1.0, seed: int = 0,
                 hidden_from: float | None = None,
                 also: tuple[tuple[Parameter, float], ...] = (), starts: bool = False,
                 columns: bool = False, beyond: float = 0.0):
        self.hidden, self.hidden_value = hidden, hidden_value
        self.beyond = beyond  # the share of the hidden effect's signature that no candidate
        # holds (the truth's alone): its signature is sqrt(1 - b^2) x the candidate's of that
        # name + b x one of its own, as a partial fault plane or an end-point shift is to the
        # library's full plane or exponent
        self.columns = columns  # a box of columns (all layers): the sum of its columns'
        # signatures, so that overlapping boxes correlate, scaled to a named signature's
        # size; a column acts on a well as exp(-d^2 / 18), d its distance (cells) to the
        # well's column in the synthetic deck
        self.also = also  # more hidden parameters (value), over the whole record
        self.hidden_from = hidden_from  # the hidden parameter acts only after this day:
        # an effect that shows late (a candidate of that name too, as a layer the flood
        # reaches late) or, ``starts``, a change at that day (the truth's alone)
        self.starts = starts
        self.seed = seed
        self.days = np.arange(1, 61) * 30.0
        self.wells = ("PROD1", "PROD2", "PROD3", "PROD4")
        self.calls = 0
        self._signatures: dict[str, np.ndarray] = {}  # name -> its signature (read only)

    WELL_COLUMNS = {"PROD1": (6, 11), "PROD2": (15, 10), "PROD3": (9, 5), "PROD4": (12, 17)}
    QUANTITIES = ("WBHP", "WWCT", "WGOR", "WOPR", "WWPR", "WGPR")

    def box_signature(self, p: Parameter) -> np.ndarray:
        i0, i1, j0, j1 = p.box[:4]
        near = np.repeat([[math.exp(-((i - wi) ** 2 + (j - wj) ** 2) / 18.0)
                           for wi, wj in self.WELL_COLUMNS.values()]
                          for i in range(i0, i1 + 1) for j in range(j0, j1 + 1)],
                         3 * self.days.size, axis=1)
        cols = [self.signature(f"column_{i}_{j}") for i in range(i0, i1 + 1)
                for j in range(j0, j1 + 1)]
        sig = np.sum(near * np.array(cols), axis=0)
        return sig * np.linalg.norm(cols[0]) / np.linalg.norm(sig)  # a named one's size

    def signature(self, name: str) -> np.ndarray:
        """The fixed random signature of ``name`` (drawn once, then kept: every call asks)."""
        if name not in self._signatures:
            sig = self._draw_signature(name)
            sig.flags.writeable = False
            self._signatures[name] = sig
        return self._signatures[name]

    def _draw_signature(self, name: str) -> np.ndarray:
        rng = np.random.default_rng([self.seed, sum(map(ord, name)) * 7 + len(name)])
        t = self.days / self.days[-1]
        out = []
        for w in self.wells:
            for amp in (10.0, 0.1, 0.2):  # bhp (bar), wct, relative gor
                a, b, c = rng.standard_normal(3)
                out.append(amp * (a + b * t + c * np.sin(3 * t + a)) * (rng.random() < 0.6))
        return np.concatenate(out)

    @staticmethod
    def change(p: Parameter, value: float, values: dict[str, float]) -> float:
        """Scaled change of ``p`` from its neutral value (1 for multipliers, the deck's 0 for
        the global skin, the global skin for a well's own skin)."""
        neutral = 1.0 if p.kind != "skin" else (values.get("skin", 0.0) if p.wells else 0.0)
        c = Coordinates([p])
        return float(c.to_u({p.name: value})[0] - c.to_u({p.name: neutral})[0])

    def responses(self, case, values: dict[str, float], truth: bool = False) -> pd.DataFrame:
        total = np.zeros(len(self.wells) * 3 * self.days.size)
        params = [p for p in case.space.parameters if p.name in values]
        if truth and self.hidden is not None:  # only the truth hides it
            params.append(self.hidden)
            values = {**values, self.hidden.name: self.hidden_value}
        if truth:
            params += [p for p, _ in self.also]
            values = {**values, **{p.name: v for p, v in self.also}}
        for p in params:
            sig = (self.box_signature(p) if self.columns and p.box is not None
                   and p.box[:4] != (1, 20, 1, 20) else self.signature(p.name))
            if p.kind == "wpimult" and p.start_day is not None:  # a skin change from a date
                sig = -self.signature(f"skin_{p.wells[0]}") * np.tile(
                    self.days > p.start_day, sig.size // self.days.size)
            if truth and self.beyond and p is self.hidden:
                own = self.signature(f"{p.name}~beyond")
                sig = math.sqrt(1.0 - self.beyond ** 2) * sig + self.beyond * own * (
                    np.linalg.norm(sig) / np.linalg.norm(own))
            if self.hidden_from is not None and self.hidden is not None \
                    and p.name == self.hidden.name and (truth or not self.starts):
                sig = sig * np.tile(self.days > self.hidden_from, sig.size // self.days.size)
            total += sig * self.change(p, values[p.name], values)
        n = self.days.size
        series = []  # per well: WBHP, WWCT, WGOR, WOPR, WWPR, WGPR, n days each
        for k, w in enumerate(self.wells):
            bhp = 200 - 0.02 * self.days + total[(3 * k) * n:(3 * k + 1) * n]
            wct = np.clip(0.3 + total[(3 * k + 1) * n:(3 * k + 2) * n], 0, 1)
            gor = 100 * (1 + 0.5 * self.days / 1800) * np.exp(total[(3 * k + 2) * n:(3 * k + 3) * n])
            oil = np.full(n, 100.0)
            series += [bhp, wct, gor, oil, oil * wct / (1 - wct), oil * gor]
        # one frame from whole columns (a frame per series and a concat took half the time
        # of a linear diagnosis)
        return pd.DataFrame({"well": np.repeat(self.wells, len(self.QUANTITIES) * n),
                             "days": np.tile(self.days, len(self.wells) * len(self.QUANTITIES)),
                             "quantity": np.tile(np.repeat(self.QUANTITIES, n), len(self.wells)),
                             "value": np.concatenate(series)})

    def evaluate_batch(self, case, values_list, step="run"):
        self.calls += len(values_list)
        return [SimpleNamespace(status="COMPLETE", responses=self.responses(case, v),
                                sim_time_s=0.0, reason="") for v in values_list]


def _linear_case(tmp_path, hidden=None, hidden_value=1.0, seed=0, hidden_from=None, also=(),
                 starts=False, columns=False, beyond=0.0):
    pytest.importorskip("opm.io")
    from hmcore.cases import load_case
    from hmcore.scenarios.hidden import noisy_history
    from hmcore.scenarios.synthetic import DECK_NAME
    from hmcore.scenarios.synthetic_deck import make_fields, render_deck

    field_rng, _ = np.random.default_rng(0).spawn(2)
    (tmp_path / DECK_NAME).write_text(render_deck(make_fields(field_rng), 0))
    sim = LinearSimulator(hidden, hidden_value, seed, hidden_from, also, starts, columns,
                          beyond)
    case0 = SimpleNamespace(space=ParameterSpace.reference())
    truth = {"poro_mult": 1.05, "permx_mult": 1.5, "permy_mult": 0.7, "permz_mult": 0.6,
             "skin": 4.0}
    obs = noisy_history(sim.responses(case0, truth, truth=True), np.random.default_rng(seed))
    obs.to_csv(tmp_path / "observed.csv", index=False)
    (tmp_path / "case.toml").write_text(f'[case]\nname = "linear"\ndeck = "{DECK_NAME}"\n'
                                        'observed = "observed.csv"\nhistory_end_days = 1350\n')
    return load_case(tmp_path / "case.toml"), sim, truth


@pytest.mark.parametrize("hidden", ["well_skin:PROD3", "layer_permeability:2",
                                    "fault_transmissibility:i10", None])
def test_diagnosis_orchestration_on_a_linear_simulator(tmp_path, hidden):
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates

    param, value = None, 1.0
    if hidden:
        from hmcore.scenarios.hidden import synthetic_deck_info

        cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                                   ParameterSpace.reference(), {"skin": 4.0})}
        param = cands[hidden].parameter
        value = {"skin": 12.0, "multiply": 0.3}[param.kind]
        value = 0.005 if hidden.startswith("fault") else value
    case, sim, truth = _linear_case(tmp_path, param, value)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=True),
                   out_dir=tmp_path / "out")
    assert set(doc["gain"]) >= {"fit_before", "fit_after", "heldout_before", "heldout_after"}
    assert (tmp_path / "out" / "diagnosis.json").is_file()
    assert (tmp_path / "out" / "report.md").read_text().startswith("# Diagnosis")
    assert list((tmp_path / "out").glob("*.png"))
    saved = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert [c["kind"] for c in saved["causes"]] == [c["kind"] for c in doc["causes"]]
    assert "none" in [c["kind"] for c in doc["causes"]]
    # the noise lines come from the false-alarm rate over this search's 32 candidates,
    # 2 dated ones and 2 x 8 moved regional boxes (Bonferroni, chi-square with 1 degree of
    # freedom)
    from scipy.stats import chi2
    assert doc["settings"]["chi2_threshold"] == doc["settings"]["fit_threshold"] == \
        pytest.approx(chi2.isf(0.003 / 50, 1))
    st = doc["statistic"]
    if hidden is None:
        assert st is None or not st["vs_none"]["beyond"]
        assert doc["causes"][0]["kind"] == "none" and doc["selected"] is None
        assert doc["gain"]["fit_after"] == doc["gain"]["fit_before"]
        assert doc["rounds"] == [] and doc["windows"] == []  # nothing to look further for
        assert "no candidate" in doc["verdict"]
    else:
        assert st["cause"] == hidden and st["vs_none"]["beyond"], st
        assert st["vs_none"]["p_family"] < 0.003 and st["vs_none"]["dof"] == 1
        assert st["vs_none"]["share"] > 0.5, st  # the whole cause: most of the excess misfit
        assert "The statistic" in (tmp_path / "out" / "report.md").read_text()
        assert doc["causes"][0]["id"] == hidden
        assert doc["selected"]["id"] == hidden
        # the second round, with it in the model, finds nothing more: one accepted cause
        assert [a["id"] for a in doc["accepted"]] == [hidden], doc["verdict"]
        assert doc["rounds"] and doc["rounds"][0]["accepted"] is None
        g = doc["gain"]
        assert g["fit_after"] < g["fit_before"] and g["heldout_after"] < g["heldout_before"]
        assert g["ssr_heldout_after"] < g["ssr_heldout_before"]


def test_a_region_beside_a_well_is_named_by_a_moved_box(tmp_path):
    """A permeability box beside PROD2 (the well at its corner, no other well inside), in a
    linear simulator where a box's signature is the sum of its columns' (each acting on the
    wells near it): the boxes centred on PROD2 and PROD4 share 16 and 21 of its 49 columns
    and score beyond noise, so the ranking tries them moved beside their wells, and the moved
    box that is the truth's is named - not a centred one, not a skin."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.candidate import well_column
    from hmcore.diagnosis.extensions import shifted_regions
    from hmcore.scenarios.hidden import synthetic_deck_info

    info = synthetic_deck_info(0, tmp_path / "d")
    moved = {c.id: c for c in shifted_regions(info, "PROD2")}
    truth = moved["regional_permeability:PROD2:i9-15:j10-16"]
    assert len(moved) == 8 and well_column(info, "PROD2") == (15, 10)
    for c in moved.values():  # the well on each moved box's edge or corner, never inside
        b = c.parameter.box
        assert b[0] <= 15 <= b[1] and b[2] <= 10 <= b[3] and c.wells == ("PROD2",)
        assert 15 in (b[0], b[1]) or 10 in (b[2], b[3])
    corner = {c.parameter.box[:4] for c in shifted_regions(info, "PROD1")}  # (6, 11)
    assert all(b[0] >= 1 and b[1] - b[0] >= 3 for b in corner) and len(corner) == 8
    case, sim, _ = _linear_case(tmp_path, truth.parameter, 0.3, columns=True)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False))
    ranked = {c["id"]: c for c in doc["ranking"]["candidates"]}
    assert set(moved) <= set(ranked), "the moved boxes of PROD2 were not probed"
    assert doc["selected"]["id"] == truth.id, doc["verdict"]
    assert [a["id"] for a in doc["accepted"]] == [truth.id]
    # not asked for: no moved box is probed, and the centred box cannot name it
    off = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False,
                                                                       region_shifts=0))
    assert not set(moved) & {c["id"] for c in off["ranking"]["candidates"]}
    assert off["gain"]["fit_after"] > doc["gain"]["fit_after"]


@pytest.mark.parametrize("generator,value,remains,beyond", [
    ("partial_fault", 0.005, True, 0.6), ("relperm_endpoint", 0.5, False, 0.6),
    ("relperm_scaling", 0.5, False, 0.0)])
def test_an_effect_the_library_holds_in_part_is_named_by_its_nearest_candidate(
        tmp_path, generator, value, remains, beyond):
    """Stand-ins for the generators whose effect a library candidate holds only in part: a
    barrier on part of a plane off the library's midlines (``partial_fault``) and the water
    curve's end point moved (``relperm_endpoint``). The hidden signature is 0.8 that of the
    candidate a right answer names (the plane that parts the producers the same way; the krw
    exponent) and 0.6 one of its own, which no candidate holds: that candidate is named and
    accepted, and the generator's own judge says found. A scaled curve (``relperm_scaling``,
    the gas one at seed 31) the library holds whole, with the factor of that curve. (Which
    candidate that is - the
    generator's ``expect_ids`` - is taken as given here; that it parts the producers as the
    hidden plane does is tested with the generators.) Where the part no candidate holds
    stays beyond noise (the barrier; the end point's is weaker and the globals absorb it),
    the verdict says that something no family explains remains (issue 18, point 3)."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.generators import generate
    from hmcore.scenarios.judge import judge_effects
    from hmcore.scenarios.hidden import synthetic_deck_info
    from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH

    info = synthetic_deck_info(0, tmp_path / "d")
    space = ParameterSpace.reference()
    (effect,) = generate(generator, 31, info, space, dict(SYNTHETIC_TRUTH))
    # the candidate a right answer names: the plane; the exponent for a moved end point, the
    # factor for a scaled curve
    right = effect.candidate.details["expect_ids"][-1 if generator == "relperm_scaling" else 0]
    cands = {c.id: c for c in build_candidates(info, space, {"skin": 4.0})}
    case, sim, _ = _linear_case(tmp_path, cands[right].parameter, value, beyond=beyond)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False))
    assert doc["causes"][0]["id"] == right, doc["verdict"]
    assert doc["accepted"] and doc["accepted"][0]["id"] == right, doc["verdict"]
    assert judge_effects(doc, [effect])["found"], doc["verdict"]
    if remains:  # the part no candidate holds is beyond noise: the verdict says so
        assert "no family explains" in doc["verdict"], doc["verdict"]
        assert doc["statistic"]["vs_none"]["share"] < 0.8


def test_a_cause_that_stops_at_an_open_end_of_its_range_is_flagged(tmp_path):
    """PROD3's skin hidden at 45, beyond the candidate's range (up to 30): the recalibrated
    skin stops at 30 and is accepted, and the verdict warns that it may stand in for something
    else (on the generator sweep such fits stood in for a moved contact). The ends that are a
    physical limit (a sealed fault, a vertical barrier) are not open: a fit there is a
    complete effect, with no warning."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.candidate import open_end
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info
    from hmcore.diagnosis.report import markdown_report

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    skin, fault = cands["well_skin:PROD3"], cands["fault_transmissibility:i10"]
    kv = cands["vertical_permeability:1"]
    assert open_end(skin, skin.parameter.high, 0.01) == "high"
    assert open_end(skin, 0.5 * (skin.parameter.low + skin.parameter.high), 0.01) is None
    assert open_end(fault, fault.parameter.low, 0.01) is None  # sealed: a limit, not an end
    assert open_end(kv, kv.parameter.low, 0.01) is None and \
        open_end(kv, kv.parameter.high, 0.01) == "high"
    assert open_end(skin, skin.parameter.high, -1.0) is None  # the warning switched off
    case, sim, _ = _linear_case(tmp_path, skin.parameter, 45.0)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False))
    assert doc["selected"]["id"] == "well_skin:PROD3", doc["verdict"]
    assert doc["candidates_recalibrated"]["well_skin:PROD3"]["open_end"] == "high"
    assert "well_skin:PROD3 stopped at the high end of its range" in doc["verdict"]
    assert doc["causes"][0]["evidence"].endswith("confirms it") and \
        "at the high end of its range" in doc["causes"][0]["evidence"]
    assert "stopped at the high end of its range" in markdown_report(doc)
    (tmp_path / "in").mkdir()
    case, sim, _ = _linear_case(tmp_path / "in", skin.parameter, 12.0)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False))
    assert doc["selected"]["id"] == "well_skin:PROD3" and "end of its range" not in doc["verdict"]


def test_a_candidate_under_the_line_is_confirmed_by_its_recalibration(tmp_path):
    """The score test is linear; a candidate it puts above the screen but under the line is
    still recalibrated, and ranks above ``none`` when the recalibrated fit drops beyond noise.
    (The line is raised out of reach here so that only the screen lets the effect through.)"""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    case, sim, _ = _linear_case(tmp_path, cands["well_skin:PROD3"].parameter, 12.0)
    settings = DiagnosisSettings(chi2_threshold=1e9, screen_threshold=8.0, plots=False)
    doc = diagnose(case, sim.evaluate_batch, settings=settings)
    assert doc["ranking"]["beyond_noise"] == []
    assert "well_skin:PROD3" in doc["ranking"]["screened"]
    assert doc["causes"][0]["id"] == "well_skin:PROD3"
    assert doc["selected"]["id"] == "well_skin:PROD3"
    below = [c["id"] for c in doc["causes"]]
    screened_rejected = [k for k in doc["ranking"]["screened"][:4] if k != "well_skin:PROD3"
                         and not doc["candidates_recalibrated"][k]["fit_beyond_noise"]]
    assert all(below.index(k) > below.index("none") for k in screened_rejected)


@pytest.mark.parametrize("before,after,e_before,e_after,n,ok,quiet", [
    (813.0, 589.0, 0.010, 0.008, 400, True, False),   # a signal in the held-back data, explained
    (813.0, 851.0, 0.010, 0.008, 400, False, False),  # E better but the SSR worse: rejected
    (813.0, 809.0, 0.010, 0.008, 400, False, False),  # not beyond noise
    # synthetic layer_permeability seed 11: the held-back history was within noise already
    (226.7, 232.4, 0.004806, 0.004439, 352, True, True),
    (226.7, 240.0, 0.004806, 0.004439, 352, False, True),  # spoils it beyond noise
    (226.7, 220.0, 0.004806, 0.004900, 352, False, True),  # E worse
    (226.7, 220.0, 0.004806, 0.004000, 0, False, False),   # nothing held back
    # PUNQ-S3, aquifer 2 x9.2 hidden (whole schedule): E rises for the truth itself (noisy
    # water and gas rates dominate it), the whitened SSR drops decisively: confirmed
    (1989.8, 702.6, 0.00789, 0.00889, 282, True, False),
    # E rises and the SSR drop (53) is under 3 sd of the chi-square of 400 points (85)
    (813.0, 760.0, 0.010, 0.011, 400, False, False),
    # a decisive drop, but E rises by more than a quarter (a wrong fix of the BHP that
    # spoils the rates: synthetic, a box around PROD4 for a fault, E 0.0244 -> 0.0397)
    (1939.0, 1700.0, 0.02443, 0.03973, 300, False, False),
])
def test_held_back_confirmation_rule(before, after, e_before, e_after, n, ok, quiet):
    from hmcore.diagnosis.confirmation import heldout_confirms
    from hmcore.diagnosis.settings import DiagnosisSettings

    assert heldout_confirms(before, after, e_before, e_after, n, DiagnosisSettings()) == (ok, quiet)


def test_an_effect_only_the_held_back_history_shows_is_found_on_a_later_window(tmp_path):
    """Nothing in the fitted history points to a cause (the effect starts after it): the
    first window ranks `none` and finds the held-back history missed beyond noise (PUNQ-S3's
    hidden fault / relperm sweep cases behaved like this). Without a later origin that is the
    answer, with the warning; by default the diagnosis fits to a later origin and names the
    effect there. A control with nothing hidden never looks further."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    case, sim, _ = _linear_case(tmp_path, cands["well_skin:PROD3"].parameter, 30.0,
                                hidden_from=1350.0)
    short = diagnose(case, sim.evaluate_batch,
                     settings=DiagnosisSettings(plots=False, later_origins=()))
    assert short["causes"][0]["kind"] == "none" and short["selected"] is None
    assert not short["heldout_within_noise"], (short["gain"], short["verdict"])
    assert "does NOT fit the held-back history within noise" in short["verdict"]
    assert short["windows"] == [] and "no later origin" in short["no_later_window"]
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False))
    assert doc["windows"][0]["first_cause"] == "none"
    assert doc["selected"]["id"] == "well_skin:PROD3", doc["verdict"]
    assert doc["named_on"]["fitted_to_day"] > 1350
    (tmp_path / "c").mkdir()
    case_c, sim_c, _ = _linear_case(tmp_path / "c")
    control = diagnose(case_c, sim_c.evaluate_batch, settings=DiagnosisSettings(plots=False))
    assert control["heldout_within_noise"] and "NOT" not in control["verdict"]
    assert control["causes"][0]["kind"] == "none" and control["windows"] == []


def test_the_origin_rolls_on_until_a_window_names_the_cause(tmp_path):
    """A rolling origin: the effect starts after the first later window ends too (85 % of the
    record; windows end at 1350, at 80 % and at 90 %). The 80 % window sees nothing of it in
    its fitted history and still misses its held-back history, so the diagnosis goes on to the
    90 % window, which names it; each window is listed in time order. With the 80 % window
    alone the answer stays unnamed and says why it stopped."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info
    from hmcore.diagnosis.rounds import diagnose_all

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    (tmp_path / "p").mkdir()
    probe, _, _ = _linear_case(tmp_path / "p")  # the record's span
    days = probe.informative.days.to_numpy(float)
    d0, d1 = float(days.min()), float(days.max())
    start = d0 + 0.85 * (d1 - d0)
    case, sim, _ = _linear_case(tmp_path, cands["well_skin:PROD3"].parameter, 30.0,
                                hidden_from=start)
    one = diagnose(case, sim.evaluate_batch,
                   settings=DiagnosisSettings(plots=False, later_origins=(0.8,)),
                   out_dir=tmp_path / "one")
    assert [w["fitted_to_day"] for w in one["windows"]] == [1350, pytest.approx(
        d0 + 0.8 * (d1 - d0))]
    assert not one["accepted"] and one["named_on"] is None
    assert "no later origin" in one["no_further_window"], one["no_further_window"]
    assert "No further window: no later origin" in (tmp_path / "one" / "report.md").read_text()
    steps: list[str] = []
    doc = diagnose_all(case, sim.evaluate_batch,
                       settings=DiagnosisSettings(plots=False, later_origins=(0.8, 0.9)),
                       on_step=lambda name, d: steps.append(name)).document
    # each window's steps are stored apart: the second's later-..., the third's later3-...
    assert {"calibration", "later-calibration", "later3-calibration",
            "later3-recalibration"} <= set(steps), steps
    ends = [w["fitted_to_day"] for w in doc["windows"]]
    assert ends == [1350, pytest.approx(d0 + 0.8 * (d1 - d0)),
                    pytest.approx(d0 + 0.9 * (d1 - d0))], doc["windows"]
    assert [w["accepted"] for w in doc["windows"][:2]] == [[], []]
    assert doc["selected"]["id"] == "well_skin:PROD3", doc["verdict"]
    assert doc["named_on"]["fitted_to_day"] == ends[2] > start
    assert "fitted to days 1350 and" in doc["verdict"]
    with pytest.raises(ValueError, match="later_origins.*must increase"):
        DiagnosisSettings(later_origins=(0.9, 0.8))


def test_a_productivity_change_from_a_date_is_named_with_its_start(tmp_path):
    """PROD3's completion changes at day 900, inside the fitted window (to day 1350): the
    date scan of its well-skin probe finds the start, the dated candidate (WPIMULT from that
    report day) gets its own probe, and it is the accepted cause, not the skin it would be
    without a date. A control's scans stay under the Bonferroni line."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    case, sim, _ = _linear_case(tmp_path, cands["well_skin:PROD3"].parameter, 12.0,
                                hidden_from=900.0, starts=True)
    settings = DiagnosisSettings(plots=False, max_causes=1)
    doc = diagnose(case, sim.evaluate_batch, settings=settings)
    dating = {d["well"]: d for d in doc["ranking"]["dating"]}
    assert dating["PROD3"]["dated"] and abs(dating["PROD3"]["day"] - 900) <= 31, dating
    assert not any(d["dated"] for w, d in dating.items() if w != "PROD3"), dating
    first = doc["causes"][0]
    assert first["kind"] == "productivity_change" and first["wells"] == ["PROD3"], doc["verdict"]
    assert abs(first["start_day"] - 900) <= 31
    assert doc["selected"]["id"] == first["id"]
    assert doc["accepted"][0]["start_day"] == first["start_day"]
    assert doc["statistic"]["cause"] == first["id"] and doc["statistic"]["vs_none"]["dof"] == 2
    # its factor and its date: the line is chi-square(2) at the one-parameter line's tail
    from scipy.stats import chi2
    line = chi2.isf(chi2.sf(doc["settings"]["fit_threshold"], 1), 2)
    assert doc["statistic"]["vs_none"]["line"] == pytest.approx(line)
    assert doc["candidates_recalibrated"][first["id"]]["fit_line"] == pytest.approx(line)
    assert "from day" in doc["verdict"]
    g = doc["gain"]
    assert g["heldout_after"] < g["heldout_before"]
    (tmp_path / "c").mkdir()
    case_c, sim_c, _ = _linear_case(tmp_path / "c")
    control = diagnose(case_c, sim_c.evaluate_batch, settings=settings)
    assert not any(d["dated"] for d in control["ranking"]["dating"]), control["ranking"]["dating"]
    assert control["causes"][0]["kind"] == "none"


@pytest.mark.parametrize("strength", [1.3, 1.6, 0.5])
def test_an_effect_of_no_family_is_unexplained_and_localised(tmp_path, strength):
    """A hidden change no candidate family makes (here a parameter named like none of them,
    signature, acting over the whole record): at x1.3 no candidate fits it beyond noise; at
    x1.6 a well skin fits part of it beyond noise but the held-back history vetoes it. Either
    way nothing is accepted and the answer is `unexplained`, localised at the wells and
    responses where the calibrated model misses in the fitted window - not a bare `none`, not
    the rejected skin. Known limit (issue 18): at x0.5 a well skin and a region at PROD4 fit
    part of it and the held-back history confirms both; the verdict then says each removes
    only a small share of the misfit beyond noise (21 % for the skin)."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose

    pvt = Parameter(name="pvt_shift", kind="multiply", keywords=("NTG",), low=0.5, high=2.0)
    case, sim, _ = _linear_case(tmp_path, pvt, strength)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False),
                   out_dir=tmp_path / "out")
    if strength == 0.5:  # the known limit: named, but said to be partial
        assert doc["accepted"] and doc["statistic"]["vs_none"]["share"] < 0.5, doc["statistic"]
        assert "of the fitted misfit beyond noise: something else acts too" in doc["verdict"]
        return
    first = doc["causes"][0]
    assert first["kind"] == "unexplained" and doc["selected"] is None, doc["verdict"]
    touched = [w for k, w in enumerate(sim.wells)
               if np.abs(sim.signature("pvt_shift").reshape(4, -1)[k]).max() > 0]
    assert first["wells"] and set(first["wells"]) <= set(touched), first["description"]
    assert "heldout" not in {f["period"] for f in first["where"]}
    assert doc["verdict"].startswith("unexplained: ")
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Unexplained: where the model misses" in report


def test_budget_caps_the_simulator_calls_and_says_when_the_ranking_cannot_fit(tmp_path):
    from hmcore.diagnosis import DiagnosisSettings, diagnose

    case, sim, _ = _linear_case(tmp_path)
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(budget=60, plots=False))
    assert doc["cost"]["simulations"] == sim.calls <= 60
    sim2 = LinearSimulator()
    with pytest.raises(ValueError, match="cannot cover the minimum of 45"):
        diagnose(case, sim2.evaluate_batch, settings=DiagnosisSettings(budget=25, plots=False))
    assert sim2.calls == 0  # refused before any simulation


def test_cli_printing_of_a_diagnosis(tmp_path):
    """What ``hmflow diagnose`` prints: ranked causes, the selected extension, the gain and the
    path of diagnosis.json (the flow itself runs in test_diagnosis_hidden.py)."""
    from rich.console import Console

    from flows.diagnose import print_diagnosis
    from hmcore.diagnosis import diagnose

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    case, sim, _ = _linear_case(tmp_path, hidden, 12.0)
    doc = diagnose(case, sim.evaluate_batch, out_dir=tmp_path / "out")
    result = {**doc, "diagnosis_path": str(tmp_path / "out" / "diagnosis.json"),
              "report_path": str(tmp_path / "out" / "report.md")}
    console = Console(width=150, record=True)
    print_diagnosis(result, console)
    text = console.export_text()
    assert "Ranked causes" in text and "well_skin" in text and "PROD3" in text
    assert "selected: well_skin (well_skin:PROD3)" in text
    assert "fitted" in text and "held back" in text and "diagnosis.json" in text
    # the answer by the evidence: the skin carries the weight alone, in the terminal and the
    # report (issue 46)
    assert doc["answer"]["members"] == ["well_skin:PROD3"], doc["answer"]["text"]
    assert "By the evidence: one cause dominates" in text and "well_skin:PROD3 *" in text
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## The answer, by the evidence" in report and "The data support well_skin:PROD3" \
        in report


def test_the_campaign_report_carries_the_diagnosis_and_from_campaign_keeps_to_its_case(tmp_path,
                                                                                       capsys,
                                                                                       monkeypatch):
    """`hmflow report` rebuilds a campaign's report from stored artifacts: with a diagnosis
    stored in the campaign (its gain, ranking and plots) and for a campaign that is a
    diagnosis alone; `--from-campaign` starts from the campaign's best on its own case and
    refuses another (real store, real files; the linear stand-in makes the diagnosis)."""
    from flows.diagnose import campaign_start
    from hmcore.diagnosis import diagnose
    from storage import ArtifactStore
    from tasks.case import prepare_deck
    from tasks.diagnose import store_step
    from tasks.results import report

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    (tmp_path / "c").mkdir()
    case, sim, truth = _linear_case(tmp_path / "c", hidden, 12.0)
    doc = diagnose(case, sim.evaluate_batch, out_dir=tmp_path / "out")
    store_root = str(tmp_path / "store")
    store = ArtifactStore(store_root)
    prepare_deck.fn(case, str(case.source), store_root, "linear-diagnosis")
    with pytest.raises(FileNotFoundError, match="no stored results and no diagnosis"):
        report.fn(store_root, "linear-diagnosis", publish_prefect_artifacts=False)
    files = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    store_step.fn(store_root, "linear-diagnosis", "diagnosis-report", {"n": 1}, files)
    rep = report.fn(store_root, "linear-diagnosis", publish_prefect_artifacts=False)
    text = rep.read_json("report.json")
    md = rep.file("report.md").read_text()
    assert md.startswith("# hmflow campaign `linear-diagnosis`")
    assert "## Diagnosis of case `linear`" in md and "### Gain" in md and "### Ranked causes" in md
    assert "well_skin" in md and doc["verdict"] in md
    assert text["diagnosis"]["selected"] == doc["selected"]["id"] == "well_skin:PROD3"
    assert text["calls"] == 0 and rep.verify() == []
    assert doc["plots"] and all(p in rep.files for p in doc["plots"])  # the plots travel along

    def no_drawing(*args, **kwargs):
        raise AssertionError("a report-only rerun of the same inputs drew its figures again")

    monkeypatch.setattr("tasks.results.render", no_drawing)  # the stored report, nothing drawn
    again = report.fn(store_root, "linear-diagnosis", publish_prefect_artifacts=False)
    assert again.reused and again == rep
    from hmflow.cli.campaign import print_report as _print_report  # what `hmflow report` prints for it

    _print_report(Path(store_root), "linear-diagnosis")
    printed = " ".join(capsys.readouterr().out.split())
    assert "no calibration campaign under this name" in printed
    assert "diagnosis: selected well_skin:PROD3" in printed

    # a campaign with an archived best: the diagnosis starts there, on the campaign's case
    with pytest.raises(LookupError, match="no archived best case"):
        campaign_start(store, "linear-diagnosis")
    store.put_files("linear-diagnosis", "best", {"index": 0}, {"params.json": truth}, "test")
    ref, start = campaign_start(store, "linear-diagnosis")
    assert Path(ref) == case.source and start == truth
    other = tmp_path / "other"
    other.mkdir()
    for f in (tmp_path / "c").iterdir():
        if f.is_file():
            (other / f.name).write_bytes(f.read_bytes())
    obs = pd.read_csv(other / "observed.csv")
    obs.loc[0, "value"] += 1.0  # another history
    obs.to_csv(other / "observed.csv", index=False)
    with pytest.raises(ValueError, match="differs from it \\(observed\\)"):
        campaign_start(store, "linear-diagnosis", str(other / "case.toml"))


def _restart_settings(**kw):
    """Settings that leave the warm-started recalibration where it starts (no line search, no
    LM step, no refinement) and count every global as at its bound, so that the restart from
    the deck's values alone can move the extended model."""
    from hmcore.diagnosis import DiagnosisSettings

    return DiagnosisSettings(**{"plots": False, "line_search": (), "refine_top": 0,
                                "near_bound": 1.0, "recalibration": LMSettings(max_evaluations=0),
                                **kw})


def test_restart_from_the_deck_values_counts_when_only_the_candidate_makes_the_gain(tmp_path):
    from hmcore.diagnosis import diagnose

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    case, sim, _ = _linear_case(tmp_path, hidden, 12.0)
    doc = diagnose(case, sim.evaluate_batch, settings=_restart_settings())
    conf = doc["candidates_recalibrated"]["well_skin:PROD3"]
    restart = conf["restart"]
    assert restart["accepted"], restart
    assert restart["ssr_fit"] < restart["ssr_fit_warm"]
    assert restart["ssr_fit_neutral"] >= conf["ssr_fit_before"]  # the candidate made the gain
    assert conf["ssr_fit_after"] == pytest.approx(restart["ssr_fit"])
    assert doc["selected"]["id"] == "well_skin:PROD3"
    assert any(h["note"].startswith("restart") for h in conf["history"])
    from hmcore.diagnosis.report import markdown_report

    recalibrated = markdown_report(doc).split("Recalibrated candidates", 1)[1]
    row = next(ln for ln in recalibrated.splitlines() if ln.startswith("| well_skin:PROD3"))
    assert "accepted: SSR" in row
    # restarts off (a negative margin: no global counts as at its bound)
    doc = diagnose(case, sim.evaluate_batch, settings=_restart_settings(near_bound=-1.0))
    assert doc["candidates_recalibrated"]["well_skin:PROD3"]["restart"] is None


def test_restart_is_rejected_when_the_globals_alone_beat_the_calibration(tmp_path):
    """A calibration short of its minimum (a given vector, not polished): the restart fits
    better, but so do its globals with the candidate neutral - the gain is not the
    candidate's, and the restart does not count."""
    from hmcore.diagnosis import diagnose

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    case, sim, truth = _linear_case(tmp_path, hidden, 12.0)
    poor = {**truth, "permx_mult": 3.0, "poro_mult": 0.8}
    doc = diagnose(case, sim.evaluate_batch, calibrated=poor,
                   settings=_restart_settings(polish_given=False))
    rejected = [c for c in doc["candidates_recalibrated"].values()
                if c["restart"] and "ssr_fit_neutral" in c["restart"]]
    assert rejected
    for c in rejected:
        assert not c["restart"]["accepted"]
        assert c["restart"]["ssr_fit_neutral"] < c["ssr_fit_before"]
        assert "the gain would be the globals'" in c["restart"]["reason"]
        assert c["ssr_fit_after"] > c["restart"]["ssr_fit"]  # the restart's fit is not used


def test_confirm_choice_recalibrates_every_screened_candidate_when_the_lead_is_weak():
    from hmcore.diagnosis.screening import confirm_choice
    from hmcore.diagnosis.settings import DiagnosisSettings

    s = DiagnosisSettings()
    # PUNQ-S3 layer 1 x3.6 (seed 23): the leader scores 25.6, the hidden layer 9th with 9.5
    weak = [("v4", 25.6), ("v5", 21.5), ("l5", 20.6), ("s1", 15.5), ("v2", 15.3), ("f9", 15.0),
            ("r11", 10.3), ("gas", 9.9), ("l1", 9.5), ("s5", 8.4), ("x", 8.1)]
    assert confirm_choice(weak, s) == [k for k, _ in weak[:10]]
    # a strong leader: the first four, and more while they score alike (PUNQ-S3 layer 5 x3.3)
    strong = [("a", 97.0), ("b", 95.0), ("c", 94.0), ("d", 77.3), ("e", 77.0), ("f", 60.0),
              ("g", 50.0)]
    assert confirm_choice(strong, s) == ["a", "b", "c", "d", "e"]
    assert confirm_choice([], s) == []


def test_restart_choice_takes_the_best_fits_and_every_tie_beyond_noise():
    """PUNQ-S3 with a baffle hidden in layer 2 (x0.01): the warm-started fits of the baffle in
    layer 3, the gas exponent, layer 1's permeability and the hidden baffle ended at SSR
    431.9, 432.1, 434.1 and 438.0 (base 476.7): the fitted history cannot tell them apart, so
    all are restarted, not only the two best. A fit beyond the tie band or within noise of the
    base is restarted only as one of the ``restart_top`` best."""
    from hmcore.diagnosis.refit import restart_choice
    from hmcore.diagnosis.settings import DiagnosisSettings

    warm = {0: 434.1, 1: 431.9, 2: 438.0, 3: 432.1, 4: 445.0}
    s = DiagnosisSettings()
    assert restart_choice(warm, 476.7, s) == [1, 3, 0, 2]
    assert restart_choice(warm, 476.7, DiagnosisSettings(tie_band=1.0)) == [1, 3]
    assert restart_choice(warm, 476.7, DiagnosisSettings(restart_top=5)) == [1, 3, 0, 2, 4]
    # nothing beyond noise (a control with globals at their bounds): only the restart_top best
    assert restart_choice(warm, 440.0, s) == [1, 3]
    assert restart_choice({}, 476.7, s) == []
    # more ties than restart_max (10 recalibrated when the lead is weak): the best four
    assert restart_choice({k: 430.0 + k for k in range(6)}, 476.7, s) == [0, 1, 2, 3]


def test_veto_restart_choice_takes_the_vetoed_fits_that_could_still_win():
    """PUNQ-S3 with a box around PRO-4 x3.5 hidden: the box fitted best (SSR 393.7, base 511.0)
    but predicted the held-back history worse than the base, the skin of PRO-4 fitted 409.6
    and the held-back history confirmed it; no global was at a bound. The box is restarted from
    the deck's values, the confirmed skin is not; a vetoed fit that could not outrank the
    confirmed one (beyond the tie band) or that is within noise of the base is not either."""
    from hmcore.diagnosis.refit import veto_restart_choice
    from hmcore.diagnosis.settings import DiagnosisSettings

    s = DiagnosisSettings()
    warm = {0: 409.6, 1: 393.7, 2: 418.0, 3: 425.0, 4: 500.0}
    ok = {0: True, 1: False, 2: False, 3: False, 4: False}
    # 2 is within the tie band of the confirmed 409.6, 3 is beyond it, 4 within noise of 511
    assert veto_restart_choice(warm, ok, 511.0, s) == [1, 2]
    # nothing confirmed: every vetoed fit beyond noise, best first, at most restart_max
    assert veto_restart_choice(warm, {}, 511.0, s) == [1, 0, 2, 3]
    assert veto_restart_choice(warm, {}, 511.0, DiagnosisSettings(restart_max=2)) == [1, 0]
    # every fit confirmed, or none beyond noise: no restart
    assert veto_restart_choice(warm, dict.fromkeys(warm, True), 511.0, s) == []
    assert veto_restart_choice(warm, ok, 405.0, s) == []


def test_the_held_back_history_has_the_last_word_in_the_ranking(tmp_path):
    """Of the recalibrated candidates that fit beyond noise, one the held-back history
    confirms ranks above (and is selected over) one that fits the fitted history better but
    predicts the held-back history worse (synthetic aquifer seed 13: the aquifer volume fitted
    best, SSR 603 vs 625, but raised the held-back SSR 262 -> 359; the hidden productivity
    index lowered it). The held-back verdicts are set by hand here on a real diagnosis."""
    from hmcore.diagnosis import Diagnosis, DiagnosisSettings

    hidden = Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5, high=30)
    case, sim, _ = _linear_case(tmp_path, hidden, 12.0)
    d = Diagnosis(case, sim.evaluate_batch, DiagnosisSettings(plots=False))
    d.calibrate()
    d.analyse()
    d.rank()
    d.extend()
    d.recalibrate()
    ok = sorted((k for k, v in d.confirmed.items() if v["fit_beyond_noise"]),
                key=lambda k: d.confirmed[k]["ssr_fit_after"])
    assert len(ok) >= 2, {k: v["ssr_fit_after"] for k, v in d.confirmed.items()}
    best_fit, other = ok[0], ok[1]
    for k in d.confirmed:
        d.confirmed[k]["heldout_beyond_noise"] = k == other
    doc = d.decide()
    assert doc["causes"][0]["id"] == other and doc["selected"]["id"] == other
    assert doc["causes"][1]["id"] == best_fit
    assert "the held-back history confirms it" in doc["causes"][0]["evidence"]
    assert "does not confirm it" in doc["causes"][1]["evidence"]
    # nothing confirmed by the held-back history: nothing is selected, the misfit beyond
    # noise is `unexplained` (localised), and the best fit leads the rejected ones
    d.confirmed[other]["heldout_beyond_noise"] = False
    doc = d.decide()
    assert doc["selected"] is None and doc["causes"][0]["kind"] == "unexplained"
    assert doc["causes"][0]["wells"], doc["causes"][0]["description"]  # where it misses
    assert doc["causes"][1]["id"] == best_fit
    assert doc["verdict"].startswith("unexplained: ") and f"Rejected {best_fit}" in doc["verdict"]


def test_judge_counts_the_whitened_held_back_misfit_only_where_the_truth_cannot_lower_e():
    """A found effect must lower the held-back E - unless the truth itself scores no better
    held-back E than the calibrated base (the noise decides E there: PUNQ-S3, aquifer 2 x9.2,
    truth 0.00876 against the base's 0.00789); then the whitened held-back SSR must drop."""
    from hmcore.diagnosis.candidate import Candidate
    from hmcore.scenarios.effects import HiddenEffect
    from hmcore.scenarios.judge import judge

    par = Parameter(name="aquifer_perm2", kind="item_multiply", low=0.05, high=20.0,
                    keywords=("AQUCT",), item=4, match="2")
    cand = Candidate(id="aquifer_strength:AQUCT:4:2", kind="aquifer_strength", parameter=par)
    effect = HiddenEffect(cand, 9.16)
    first = {"kind": "aquifer_strength", "wells": [], "layers": [], "id": cand.id, "chi2": 233.0}
    gain = {"fit_before": 0.00172, "fit_after": 0.00137, "heldout_before": 0.00789,
            "heldout_after": 0.00889, "ssr_heldout_before": 1989.8, "ssr_heldout_after": 702.6}
    doc = {"causes": [first], "selected": {"id": cand.id}, "gain": gain, "verdict": "accepted"}
    j = judge(doc, effect, {"truth_E_heldout": 0.00876})
    assert j["found"] and j["heldout_improved"] and not j["heldout_E_improved"]
    # the truth does better than the base on E: E must drop, and it rose
    assert not judge(doc, effect, {"truth_E_heldout": 0.0070})["found"]
    assert not judge(doc, effect)["found"]  # no signal recorded: E alone
    # E cannot tell, but the whitened misfit rose too
    worse = {**doc, "gain": {**gain, "ssr_heldout_after": 2100.0}}
    assert not judge(worse, effect, {"truth_E_heldout": 0.00876})["found"]
    # E dropped: found, whatever the truth scores
    better = {**doc, "gain": {**gain, "heldout_after": 0.0050}}
    assert judge(better, effect, {"truth_E_heldout": 0.0040})["found"]


def test_two_hidden_effects_are_both_accepted_each_with_its_gain(tmp_path):
    """Two effects of different kinds (a well's skin and a layer's permeability): round 1
    accepts one, round 2 - with it in the model - the other, each with its own gain, and the
    whole gain is that of the pair (issue 18, point 2)."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    skin, layer = cands["well_skin:PROD3"], cands["layer_permeability:2"]
    case, sim, _ = _linear_case(tmp_path, skin.parameter, 12.0,
                                also=((layer.parameter, 0.3),))
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False),
                   out_dir=tmp_path / "out")
    accepted = doc["accepted"]
    assert {a["id"] for a in accepted} == {skin.id, layer.id}, doc["verdict"]
    assert [a["round"] for a in accepted] == [1, 2]
    assert [c["id"] for c in doc["causes"][:2]] == [a["id"] for a in accepted]
    for a in accepted:  # each its own gain, over the model without it
        assert a["gain"]["fit_after"] < a["gain"]["fit_before"], a
    assert accepted[1]["gain"]["fit_before"] == pytest.approx(accepted[0]["gain"]["fit_after"],
                                                               rel=1e-6)
    g = doc["gain"]
    assert g["fit_after"] <= accepted[1]["gain"]["fit_after"] * (1 + 1e-9)
    assert g["heldout_after"] < g["heldout_before"]
    assert set(doc["selected"]["values"]) >= {skin.name, layer.name}
    assert doc["rounds"][0]["accepted"] == accepted[1]["id"]
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Accepted causes" in report and layer.id in report and skin.id in report
    assert "incomplete" not in doc["verdict"]  # the pair leaves noise in the held-back data
    # by the evidence, the pair (weighed with round 1's explanations) carries the weight alone
    # and the judge counts it right (issue 46)
    from hmcore.scenarios.effects import HiddenEffect
    from hmcore.scenarios.judge import judge_effects

    assert doc["answer"]["members"] == [f"{accepted[0]['id']}+{accepted[1]['id']}"], \
        doc["answer"]["text"]
    j = judge_effects(doc, [HiddenEffect(skin, 12.0), HiddenEffect(layer, 0.3)])
    assert j["outcome"] == "right" and j["set_size"] == 1
    # one cause only when asked: the second is not looked for
    one = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False,
                                                                       max_causes=1))
    assert len(one["accepted"]) == 1 and one["rounds"] == []
    assert one["no_second_round"] == "max_causes is 1"


def test_accepted_causes_that_leave_the_held_back_history_beyond_noise_say_so():
    from hmcore.diagnosis import DiagnosisSettings
    from hmcore.diagnosis.confirmation import heldout_noise_line
    from hmcore.diagnosis.forward import remaining_text

    s = DiagnosisSettings()
    line = heldout_noise_line(260, s)
    assert 260 < line < 731
    text = remaining_text(731.0, 260, s, "well_skin:PROD1 and well_skin:PROD4", pair=True)
    assert "incomplete" in text and "731" in text and f"{line:.0f}" in text
    assert "third cause" in text
    assert "another shape" in remaining_text(731.0, 260, s, "well_skin:PROD1")
    assert remaining_text(line - 1, 260, s, "x") == ""
    assert remaining_text(731.0, 0, s, "x") == ""  # nothing measured held back


def _partial_doc(before: float, after: float, n: int = 260, fit_share: float = 0.06) -> dict:
    """A finished diagnosis: one accepted cause, round 2 found residuals no family explains."""
    unexplained = {"kind": "unexplained", "id": "unexplained", "wells": ["PROD2"],
                   "description": "PROD2 bhp misses", "evidence": "round 2: residuals"}
    skin = {"kind": "well_skin", "id": "well_skin:PROD3", "wells": ["PROD3"]}
    return {"causes": [skin, unexplained, {"kind": "none", "id": "none"}],
            "accepted": [{**skin, "round": 1}], "verdict": "accepted well_skin:PROD3",
            "gain": {"ssr_heldout_before": before, "ssr_heldout_after": after,
                     "n_heldout_measured": n, "ssr_fit_before": 1081.0,
                     "ssr_fit_after": 1081.0 - fit_share * (1081.0 - 776), "n_fit_measured": 776},
            "windows": [{"first_cause": "x"}, {"first_cause": "well_skin:PROD3"}],
            "named_on": {"fitted_to_day": 2241.0}}


@pytest.mark.parametrize("before,after,n,fit_share,leads", [
    (507.0, 482.0, 260, 0.06, True),    # 10 % held back, 6 % fitted (synthetic pvt 33)
    (513.0, 380.0, 260, 0.06, False),   # 53 % held back: a majority, the cause stays first
    (513.0, 320.0, 260, 0.06, False),   # 76 %, and within noise after it (line 328)
    (400.0, 340.0, 260, 0.40, True),    # 43 % and 40 %, still beyond noise
    (507.0, 482.0, 260, 0.65, False),   # most of the fitted misfit: a partial shape's name
    (507.0, 482.0, 0, 0.06, False),     # nothing measured held back
    (320.0, 335.0, 260, 0.06, False),   # within noise before it (line 328): nothing to explain
])
def test_a_cause_explaining_a_minority_of_the_misfit_leads_with_unexplained(
        before, after, n, fit_share, leads):
    from hmcore.diagnosis import DiagnosisSettings
    from hmcore.diagnosis.decision import lead_unexplained

    s = DiagnosisSettings()
    doc = _partial_doc(before, after, n, fit_share)
    out = lead_unexplained(doc, s)
    assert [c["id"] for c in out["causes"]][:2] == (
        ["unexplained", "well_skin:PROD3"] if leads else ["well_skin:PROD3", "unexplained"])
    assert out["accepted"] == doc["accepted"]  # still in the model, a partial answer
    if leads:
        share = (before - after) / (before - n)
        assert out["lead"]["heldout_share"] == pytest.approx(share)
        assert out["verdict"].startswith("unexplained: PROD2 bhp misses")
        assert f"only {100 * share:.0f} %" in out["verdict"]
        assert f"and {100 * fit_share:.0f} % of the fitted one" in out["verdict"]
        assert out["windows"][-1]["first_cause"] == "unexplained"
        assert lead_unexplained(out, s) is out  # idempotent
    else:
        assert out is doc and "lead" not in out
    if leads:  # the judge of one library effect reads a partial answer as judge_effects does
        from hmcore.scenarios.effects import HiddenEffect
        from hmcore.scenarios.judge import judge
        from hmcore.diagnosis.candidate import Candidate

        skin = Candidate("well_skin:PROD3", "well_skin",
                         Parameter(name="skin_PROD3", kind="skin", wells=("PROD3",), low=-5,
                                   high=30), ("PROD3",), (), "PROD3's skin", 0.0, 6.0)
        out = {**out, "selected": out["accepted"][0],
               "gain": {**out["gain"], "fit_before": 0.01, "fit_after": 0.009,
                        "heldout_before": 0.02, "heldout_after": 0.018}}
        for c in out["causes"]:
            c.setdefault("chi2", None)
        assert judge(out, HiddenEffect(skin, 12.0))["ranked_first"]
        assert not judge({**out, "lead": None}, HiddenEffect(skin, 12.0))["ranked_first"]
    wide = DiagnosisSettings(partial_share=0.05)
    assert lead_unexplained(_partial_doc(507.0, 482.0), wide)["causes"][0]["id"] == \
        "well_skin:PROD3"


def test_the_sweep_evidence_of_an_effect_of_no_family_leads_with_unexplained_once_set_again():
    """The kept evidence of the sweep's synthetic pvt 33 (a less dissolved-gas PVT, no family;
    run before the library's end-point shifts):
    layer 1's kv was accepted, removing 10 % of the held-back misfit beyond noise; with the
    lead set again (what ``bench_diagnosis.py --rejudge`` does) the answer is `unexplained`
    and the judge counts it right."""
    import gzip

    from hmcore.diagnosis import DiagnosisSettings
    from hmcore.diagnosis.decision import lead_unexplained
    from hmcore.scenarios.judge import judge_effects
    from hmcore.scenarios.effects import load_hidden_effects

    kept = (Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "diagnosis-sweep"
            / "before-endpoint" / "evidence" / "synthetic-pvt-33")
    doc = json.loads(gzip.decompress((kept / "diagnosis.json.gz").read_bytes()))
    effects = load_hidden_effects(kept / "hidden_effect.json")
    signal = json.loads((kept / "hidden_effect.json").read_text()).get("signal")
    doc["causes"] = [c for c in doc["causes"] if c["kind"] != "unexplained"][:1] + \
        [c for c in doc["causes"] if c["kind"] == "unexplained"] + \
        [c for c in doc["causes"] if c["kind"] != "unexplained"][1:]  # as the run stored it
    doc.pop("lead", None)
    assert not judge_effects(doc, effects, signal)["found"]
    led = lead_unexplained(doc, DiagnosisSettings())
    assert led["causes"][0]["kind"] == "unexplained" and led["accepted"] == doc["accepted"]
    assert judge_effects(led, effects, signal)["found"]


def test_a_late_effect_behind_a_vetoed_cause_is_found_on_a_later_window(tmp_path):
    """A well's skin over the whole record plus a layer change that starts at the end of the
    fitted window (day 1350 of 1800). Window 1: the skin fits beyond noise but the held-back
    history (where the layer acts) vetoes it; round 2 with the skin tentatively in the model
    finds no partner (the layer leaves no trace before day 1350), so nothing is accepted -
    while the held-back history is missed beyond noise. The diagnosis takes its own advice:
    fitted to a later origin it names both, each with its gain, and says which window did
    (issue 18, points 1 and 2)."""
    from hmcore.diagnosis import DiagnosisSettings, diagnose
    from hmcore.diagnosis.candidate import KINDS
    from hmcore.diagnosis.extensions import build_candidates
    from hmcore.scenarios.hidden import synthetic_deck_info

    cands = {c.id: c for c in build_candidates(synthetic_deck_info(0, tmp_path / "d"),
                                               ParameterSpace.reference(), {"skin": 4.0})}
    skin, layer = cands["well_skin:PROD3"], cands["layer_permeability:2"]
    case, sim, _ = _linear_case(tmp_path, layer.parameter, 0.3, hidden_from=1350.0,
                                also=((skin.parameter, 12.0),))
    # the stand-in's signatures are random: a relative-permeability factor's can stand in for
    # the layer's onset, which a real curve cannot; this test is about the windows and the pair
    kinds = tuple(k for k in KINDS if k != "relative_permeability")
    doc = diagnose(case, sim.evaluate_batch, settings=DiagnosisSettings(plots=False, kinds=kinds),
                   out_dir=tmp_path / "out")
    first, later = doc["windows"]
    assert first["fitted_to_day"] == 1350 and first["accepted"] == []
    # nothing accepted on window 1: the misfit is `unexplained` first, the vetoed skin next
    assert first["first_cause"] == "unexplained" and not first["heldout_within_noise"]
    assert f"{skin.id} stays rejected" in first["verdict"]  # the tentative round 2
    assert later["fitted_to_day"] > 1350 and doc["named_on"]["fitted_to_day"] == \
        later["fitted_to_day"]
    assert {a["id"] for a in doc["accepted"]} == {skin.id, layer.id}, doc["verdict"]
    assert all(a["gain"]["fit_after"] < a["gain"]["fit_before"] for a in doc["accepted"])
    assert doc["verdict"].startswith("fitted to day 1350, nothing was accepted")
    assert doc["cost"]["simulations"] == sim.calls
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Fitted windows (rolling origin)" in report
