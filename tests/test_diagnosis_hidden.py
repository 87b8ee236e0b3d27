"""Hide an effect in the "measured" data and require the diagnosis to find it (real OPM Flow).

Each case: the truth = the five global parameters + one extension drawn by seed (kind, which
well / layer / fault plane / aquifer / table, realistic strength), realistic correlated noise;
the diagnosis runs on the unmodified base model and must rank the hidden kind (and well or
layer) first, select it, and improve the held-back misfit. A control with nothing hidden must
report ``none``.

Default run (CI): a hidden well skin in the small synthetic case's deck (`hmflow hide
--deck`), through the Prefect flow and its CLI printing, and the control with nothing hidden
on the small synthetic case. ``-m slow``: the controls on the built-in grid (3 and 7 years) and
the small case's known false alarm, two more seeded
synthetic cases (an aquifer, a layer), the full sweep, every kind on several seeds, synthetic
and PUNQ-S3 (measured data made from a truth run of PUNQS3.DATA with the effect applied), and the cases the diagnosis is known to miss today (KNOWN_MISSES: they stay
in the sweep, asserting the same, so that a fix shows up as a pass).
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import pytest

from hmcore.diagnosis.candidate import KINDS

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
pytestmark = [pytest.mark.opm]

DEFAULT_CASES = [pytest.param("aquifer_strength", 3, id="aquifer_strength-3",
                              marks=pytest.mark.slow),
                 pytest.param("layer_permeability", 4, id="layer_permeability-4",
                              marks=pytest.mark.slow)]
"""layer_permeability-4 (layer 2 x3.25) scores chi2 15.0, at the line: found since candidates
above the screen (8) are recalibrated too (fitted SSR -17.6, held-back -62). Slow since
2026-11-23: its globals end at their bounds, so it pays for the restart from the deck's values
(the suite took 27 min with it, over CI's ~25 min target). aquifer_strength-3 (3.8 min) slow
since 2026-11-25 for the same reason (the suite took 27.9 min on a clean clone of 34874f2):
the default run keeps the flow's hidden well skin (through the Prefect flow and the CLI) and
the control; `-m slow` runs both cases here and the whole sweep."""
KNOWN_MISSES: list[tuple[str, int]] = []
"""Sweep of 2026-11-22 (seeds 11, 12 of every kind + control 6): the misses are sweep cases
already - aquifer_strength-11 (a Fetkovich aquifer's PI x0.05: even the truth fits the fitted
history only 20 chi2 better than the calibrated base, the globals had absorbed it; the
held-back data tell, the recalibration cannot get there) and fault_transmissibility-12 (the
right plane ranks first, the held-back whitened SSR drops 699 -> 462 but the held-back E rises
0.00315 -> 0.00322, so it is not selected; since the second session of 2026-11-24 a decisive
held-back SSR drop confirms despite an E rise of up to 25 % - not rerun)."""
FLOW_CASE = ("well_skin", 1)
FLOW_SETTINGS = {"confirm_top": 2, "confirm_max": 2, "confirm_weak_max": 2, "near_bound": -1.0,
                 "restart_on_veto": False, "max_causes": 1}
PUNQ_DEFAULT = ("regional_permeability", 2)
"""Missed on 2026-11-22 and 2026-11-24 (7.3 min): well_skin:PRO-4 ranks above the hidden
regional box around PRO-4 (chi2 91 vs 48); recalibrated, the box fits better (SSR 393.7 vs
409.6, base 511.0) but predicts the held-back history worse (SSR 1148 vs the base's 813; the
skin 701): the calibration left the globals far from the truth (poro 0.86, permy 1.81, permz
0.53) but not at their bounds, so no restart from the deck's values. Found since the second
session of 2026-11-24 (4.9 min, 152 simulations): a best fit the held-back history vetoes is
restarted from the deck's values too; the restart ends at SSR 394.2 with the globals at the
deck's values (prior 0.0), held-back SSR 131, held-back E 0.0551 -> 0.0077. The PUNQ-S3
sweep (seed 21, every kind) of 2026-11-22 found regional_permeability (PRO-12) and well_skin
(PRO-4); on 2026-11-23, with the restart from the deck's values and up to 6 recalibrated
candidates, also aquifer_strength AQUCT 1 x5.28 (was: aquifer 2 first; now value 4.80,
held-back E 0.0117 -> 0.0033) and layer_permeability:5 x3.32 (was: well_skin:PRO-1 first, the
layer 6th by score; now value 3.39, held-back E 0.0175 -> 0.0032); since every fit within the
tie band is restarted, vertical_permeability:2 x0.01 too (was: the adjacent layer 3, whose
restart was the only one of the four tied fits; now value 0.0103 with the globals back at
1.02/0.99/1.00/1.02/5.1, held-back E 0.0179 -> 0.0068 - but layer 3's restart is as good on
the held-back SSR, 200.9 vs 200.7: a narrow call). Fault j23 (x0.0012) and the krw exponent (0.48) act after day 2200: their
signals on the fitted history read chi2 1.4 and 7 (held back 36 and 104) under the noise first
estimated from the observed series; since 2026-11-24 `hide` measures under the noise the
diagnosis estimates with the right globals, where j23 reads 16.4 once the globals absorb (at the
line; the diagnosis scored it 7 and reported `none` with the held-back warning)."""
PUNQ_WHOLE_SCHEDULE = ("aquifer_strength", 37)
PUNQ_LATE_FAULT = ("fault_transmissibility:j23", 0.0012)
LATE_FAULT_HISTORY_END = 1200.0
"""The PUNQ-S3 sweep's fault (seed 21) acts late: fitted to day 1200 its signal is chi2 6
(189 held back), under the line. Under the signal-robust noise estimate (scoring.noise) the
history to day 1600 already shows it (chi2 21, 19 once the globals absorb; the earlier estimate,
about four times too wide on BHP, read 5 there)."""
SMALL_FALSE_ALARMS = (2, 5)
"""Seeds of the small synthetic case (nothing hidden) whose diagnosis answers `unexplained`
(2026-11-28: seed 2, PROD2's GOR and gas rate biased, z = -4.1, 90 simulations; seed 5 likewise,
measured the day before): a known false alarm (issue 46). Seeds 0 and 1 answer `none` (top
chi2 4.0 and 2.6 against a line of 16.1; 60 and 111 simulations): seed 0 is the default run's
control."""
SWEEP_SEEDS = (11, 12)
PUNQ_HISTORY_END = 2200.0
PUNQ_RECORD_END = 2936.0  # the measured record of PUNQ-S3: the first 8 years
TIMES: dict[str, float] = {}


def _opm():
    try:
        import opm.io  # noqa: F401
        import opm.simulators  # noqa: F401
    except ImportError:
        pytest.skip("OPM Python packages (opm, opm-simulators) not installed")


def _signal(case_dir: Path) -> dict | None:
    """The hidden effect's signal as `hide` measured it (see :func:`effect_signal`)."""
    return json.loads((case_dir / "hidden_effect.json").read_text()).get("signal")


def assert_found(doc: dict, effect, case_dir: Path) -> None:
    """The hidden kind (and well / layer / plane / aquifer / phase) ranks first, is selected,
    and the held-back misfit improves (see :func:`hmcore.scenarios.judge.judge`; ``case_dir``
    holds hidden_effect.json with the truth's own held-back E)."""
    from hmcore.scenarios.judge import judge

    j = judge(doc, effect, _signal(case_dir))
    what = f"hidden {j['hidden']} = {j.get('value', 0):.4g}; ranked {j['ranking']}; {j['verdict']}"
    assert j["ranked_first"], what
    assert j["selected"], what
    assert j["heldout_improved"], what
    g = doc["gain"]
    assert g["fit_after"] < g["fit_before"]


def assert_found_where_visible(doc: dict, effect, case_dir: Path) -> None:
    """:func:`assert_found` when the effect shows in the fitted history (its signal, measured by
    `hide`, reaches the score test's line once the global parameters absorbed what they can)
    or was found all the same; otherwise the right answer is that nothing in the fitted history
    names a cause (a wrong one is a failure), and where
    the held-back signal is strong enough to lift the held-back misfit beyond the noise line,
    the verdict must say that the held-back history is missed."""
    from hmcore.diagnosis.decision import heldout_noise_line
    from hmcore.diagnosis.settings import DiagnosisSettings

    from hmcore.scenarios.judge import judge

    signal = _signal(case_dir)
    if signal["visible_in_fitted_history"] or judge(doc, effect, signal)["found"]:
        assert_found(doc, effect, case_dir)  # found is right even where the signal is weak
        return
    what = f"invisible {effect.candidate.id} (signal {signal}); {doc['verdict']}"
    assert doc["causes"][0]["kind"] == "none" and doc["selected"] is None, what
    held = signal.get("chi2_heldout_after_globals", signal["chi2_heldout"])
    n = signal.get("n_heldout_measured", signal["n_heldout"])
    assert held < heldout_noise_line(n, DiagnosisSettings()) - n or \
        not doc["heldout_within_noise"], what


def diagnose_synthetic(tmp: Path, kind: str | None, seed: int, layout: str = "default"):
    """Diagnose the synthetic case of ``seed`` hiding an effect of ``kind`` (None: the
    control); ``layout`` "short" or "small" (controls only): the built-in grid over 3 years
    (:data:`hmcore.scenarios.synthetic_deck.SHORT_LAYOUT`), or the small case
    (:data:`~hmcore.scenarios.synthetic_deck.SMALL_LAYOUT`)."""
    from hmcore.cases import load_case
    from hmcore.diagnosis import diagnose, local_evaluator
    from hmcore.scenarios.hidden import write_hidden_synthetic_case
    from hmcore.scenarios.synthetic import write_synthetic_case
    from hmcore.scenarios.synthetic_deck import SHORT_LAYOUT, SMALL_LAYOUT

    start = time.perf_counter()
    if layout in ("short", "small"):
        assert kind is None, f"the {layout} layout is for controls"
        grid = SHORT_LAYOUT if layout == "short" else SMALL_LAYOUT
        case_toml, effect = write_synthetic_case(tmp / "case", seed, layout=grid), None
    else:
        case_toml, effect = write_hidden_synthetic_case(tmp / "case", seed, kind)
    doc = diagnose(load_case(case_toml), local_evaluator(tmp / "runs", workers=2),
                   out_dir=tmp / "out")
    TIMES[f"synthetic-{kind}-{seed}"] = time.perf_counter() - start
    shutil.rmtree(tmp / "runs", ignore_errors=True)
    return doc, effect


def diagnose_punq(tmp: Path, kind: str, seed: int, *,
                  history_end: float | None = PUNQ_HISTORY_END,
                  record_end: float | None = PUNQ_RECORD_END):
    from hmcore.cases import load_case
    from hmcore.diagnosis import diagnose, local_evaluator
    from hmcore.scenarios.hidden import write_hidden_deck_case

    if not (PUNQ / "PUNQS3.DATA").is_file():
        pytest.skip(f"PUNQ-S3 data not found at {PUNQ}")
    start = time.perf_counter()
    truth = {"poro_mult": 1.0, "permx_mult": 1.0, "permy_mult": 1.0, "permz_mult": 1.0,
             "skin": 5.0}
    case_toml, effect = write_hidden_deck_case(tmp / "case", PUNQ / "PUNQS3.DATA", seed,
                                               truth=truth, kind=kind,
                                               history_end_days=history_end,
                                               with_sigma=False, name="punq-hidden",
                                               end_days=record_end)
    doc = diagnose(load_case(case_toml), local_evaluator(tmp / "runs", workers=2),
                   out_dir=tmp / "out")
    TIMES[f"punq-{kind}-{seed}"] = time.perf_counter() - start
    shutil.rmtree(tmp / "runs", ignore_errors=True)
    return doc, effect


# ============================================================================= default run
@pytest.mark.parametrize("kind,seed", DEFAULT_CASES)
def test_hidden_effect_is_found_in_the_synthetic_case(tmp_path, kind, seed):
    _opm()
    doc, effect = diagnose_synthetic(tmp_path, kind, seed)
    assert_found(doc, effect, tmp_path / "case")
    assert list((tmp_path / "out").glob("residuals_*.png"))


@pytest.mark.parametrize("layout,seed", [
    pytest.param("small", 0, id="small-0"),
    pytest.param("short", 5, id="short", marks=pytest.mark.slow),
    pytest.param("default", 5, id="built-in", marks=pytest.mark.slow),
    *(pytest.param("small", s, id=f"small-{s}", marks=[pytest.mark.slow, pytest.mark.xfail(
        strict=True, reason="a known false alarm (issue 46): 'unexplained', a bias at one "
        "well, where nothing is hidden")]) for s in SMALL_FALSE_ALARMS)])
def test_control_with_nothing_hidden_reports_none(tmp_path, layout, seed):
    """Nothing hidden: the diagnosis must name no cause, far from the line. The default run
    diagnoses the small synthetic case of seed 0 (SMALL_LAYOUT: the built-in case's wells,
    gas cap, aquifer and noise on 10 x 10 x 5 cells over 3 years; 60 simulations); ``-m slow``
    the built-in grid over 3 years (SHORT_LAYOUT) and the built-in case itself (7 years) with
    the sweep's seed, and the small case's known false alarms (:data:`SMALL_FALSE_ALARMS`), a
    strict xfail that a fix turns into a pass."""
    _opm()
    doc, _ = diagnose_synthetic(tmp_path, None, seed, layout)
    assert doc["causes"][0]["kind"] == "none"
    assert doc["selected"] is None and "no candidate" in doc["verdict"]
    g = doc["gain"]
    assert g["fit_after"] == g["fit_before"] and g["heldout_after"] == g["heldout_before"]
    top = max(c["chi2"] for c in doc["causes"] if c["kind"] != "none")
    assert top < doc["settings"]["chi2_threshold"] / 3  # far from the line, not just under it


@pytest.mark.slow
def test_hidden_effect_is_found_in_punq_s3(tmp_path):
    _opm()
    doc, effect = diagnose_punq(tmp_path, *PUNQ_DEFAULT)
    assert_found(doc, effect, tmp_path / "case")
    # the noise was estimated (the CSV has no sigma), close to the description's 3 bar
    levels = [lv["sigma"] for lv in doc["calibration"]["noise"]["WBHP"]["levels"]
              if lv["segment"] == "flowing"]
    assert 1.5 < sorted(levels)[len(levels) // 2] < 5.0


@pytest.mark.slow
def test_hidden_effect_is_found_in_punq_s3_where_the_truth_cannot_lower_held_back_e(tmp_path):
    """`hmflow hide --deck PUNQS3.DATA`'s defaults (the whole schedule, 75 % fitted), aquifer 2
    AQUCT permeability x9.16 (seed 37): recalibrated it fits best and the whitened held-back
    SSR falls decisively, but the held-back E rises, as the truth's own does (0.00876 against
    the calibrated base's 0.00789: noisy water and gas rates dominate E there). Found since
    2026-11-24 (5.2 min, 196 simulations); before, layer 2 was named."""
    _opm()
    doc, effect = diagnose_punq(tmp_path, *PUNQ_WHOLE_SCHEDULE, history_end=None,
                                record_end=None)
    assert_found(doc, effect, tmp_path / "case")
    assert "the held-back E does not drop" in doc["verdict"]


def test_diagnose_flow_stores_every_step_and_finds_the_hidden_effect(tmp_path, capsys,
                                                                    small_case, prefect_api,
                                                                    monkeypatch):
    """A new user's path: `hmflow hide` writes the case on the user's deck, the Prefect
    diagnose flow (simulations as tasks, two at a time) runs end to end with the CLI print,
    `hmflow reveal` compares the diagnosis with the hidden effect. Kept small for CI's time
    (every family and the default settings took 175 simulations, 7.4 min, on the built-in
    case): the deck of the small synthetic case (conftest.small_case, a fifth of the built-in
    case's simulation time) with the built-in case's true global parameters (`--set`), the
    diagnosis given them as its calibrated model (``calibrated``: phase 1 of the calibration
    skipped, the truth run once and polished by phase 2; 63 simulations instead of 78 from
    the deck's values, 2026-11-28, issue 40: suite time), the two families that both explain
    one well's pressure (`--kinds`), the two leading candidates recalibrated, no restarts,
    one cause (:data:`FLOW_SETTINGS`); `hmflow hide` on the built-in case is in the test
    below, the control (phase 1 from the deck's values, without Prefect) searches every
    family on it, the slow sweeps find every kind among all with the default settings.
    `hmflow report` uses the session's Prefect server (conftest.prefect_api)."""
    _opm()
    from rich.console import Console
    from typer.testing import CliRunner

    from flows.diagnose import STEPS, diagnose_command
    from hmcore.scenarios.effects import load_hidden_effect
    from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH
    from hmflow.cli import app
    from storage import ArtifactStore

    kind, seed = FLOW_CASE
    start = time.perf_counter()
    runner = CliRunner()
    truth = [arg for name, value in SYNTHETIC_TRUTH.items() for arg in ("--set", f"{name}={value}")]
    out = runner.invoke(app, ["hide", "--out", str(tmp_path / "case"), "--deck",
                              str(small_case.parent / "SYNTH.DATA"), *truth, "--kind", kind,
                              "--seed", str(seed)])
    assert out.exit_code == 0, out.output
    case_toml = tmp_path / "case" / "case.toml"
    assert f"hmflow diagnose --case {case_toml}" in out.output
    assert f"hmflow reveal --hidden {tmp_path / 'case' / 'hidden_effect.json'}" in out.output
    effect = load_hidden_effect(tmp_path / "case" / "hidden_effect.json")
    assert effect.kind == kind
    signal = json.loads((tmp_path / "case" / "hidden_effect.json").read_text())["signal"]
    assert signal["chi2_fit"] > 15 and signal["visible_in_fitted_history"]
    assert f"signal: chi2 {signal['chi2_fit']:.0f} on the fitted history" in out.output
    refused = runner.invoke(app, ["hide", "--out", str(tmp_path / "case"), "--kind", kind])
    assert refused.exit_code == 2 and "nothing is overwritten" in refused.output
    console = Console(width=160, record=True)
    monkeypatch.setenv("PREFECT_API_URL", prefect_api)  # no temporary server of its own
    result = diagnose_command(case=str(case_toml), storage=tmp_path / "store", workers=2,
                              campaign="hidden-skin", console=console,
                              kinds=["well_skin", "regional_permeability"],
                              settings=FLOW_SETTINGS, calibrated=dict(SYNTHETIC_TRUTH))
    TIMES[f"flow-synthetic-{kind}-{seed}"] = time.perf_counter() - start
    doc = json.loads(Path(result["diagnosis_path"]).read_text())
    assert_found(doc, effect, tmp_path / "case")
    assert doc["calibration"]["method"] == "given, polished"
    store = ArtifactStore(tmp_path / "store")
    for step in STEPS:
        assert store.latest("hidden-skin", step) is not None, step
    assert store.latest("hidden-skin", "diagnosis-report").verify() == []
    files = store.latest("hidden-skin", "diagnosis-report").files
    assert "diagnosis.json" in files and "report.md" in files
    assert any(f.startswith("residuals_") and f.endswith(".png") for f in files)
    ranking = store.latest("hidden-skin", "diagnosis-ranking").read_json("ranking.json")
    assert len(ranking["candidates"]) == len(doc["ranking"]["candidates"])
    text = console.export_text()
    assert "Ranked causes" in text and "well_skin" in text and "diagnosis.json" in text
    # the campaign's report carries the diagnosis, and `hmflow report` rebuilds it from storage
    rep = store.latest("hidden-skin", "report")
    assert result["campaign_report_path"] == str(rep.file("report.md"))
    md = rep.file("report.md").read_text()
    assert "## Diagnosis of case" in md and "### Gain" in md and effect.candidate.id in md
    assert all(p in rep.files for p in doc["plots"]) and rep.verify() == []
    again = runner.invoke(app, ["report", "--storage", str(tmp_path / "store"),
                                "--campaign", "hidden-skin"])
    assert again.exit_code == 0, again.output
    assert f"diagnosis: selected {effect.candidate.id}" in again.output
    assert result["simulations"] == doc["cost"]["simulations"]
    shown = runner.invoke(app, ["reveal", "--hidden", str(tmp_path / "case" / "hidden_effect.json"),
                                "--diagnosis", result["diagnosis_path"]])
    assert shown.exit_code == 0, shown.output
    assert "FOUND" in shown.output and effect.candidate.id in shown.output
    assert "signal of the hidden effect: chi2" in shown.output
    control = tmp_path / "control_effect.json"  # the same diagnosis judged as a control's
    control.write_text(json.dumps({"effect": None, "truth": {}}))
    wrong = runner.invoke(app, ["reveal", "--hidden", str(control),
                                "--diagnosis", result["diagnosis_path"]])
    assert wrong.exit_code == 1 and "NOT FOUND" in wrong.output


def test_effect_signal_is_zero_for_a_neutral_effect_and_names_an_invisible_one(tmp_path,
                                                                              small_case):
    """The signal of a hidden effect (truth with vs without it, whitened, real OPM runs): zero
    when the effect sits at its neutral value (the run without it reproduces the truth run);
    a different skin everywhere shows, but the global skin absorbs all of it (both on the
    small synthetic case's deck, conftest.small_case, with the built-in case's true globals);
    and on PUNQ-S3 a fault that acts only after the fitted history is reported as hardly
    visible there, with `hmflow hide` saying so."""
    _opm()
    from typer.testing import CliRunner

    from hmcore.scenarios.hidden import effect_signal
    from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH
    from hmflow.cli import app

    runner = CliRunner()
    truth = [arg for name, value in SYNTHETIC_TRUTH.items() for arg in ("--set", f"{name}={value}")]
    out = runner.invoke(app, ["hide", "--out", str(tmp_path / "neutral"), "--deck",
                              str(small_case.parent / "SYNTH.DATA"), *truth, "--seed", "3",
                              "--candidate", "well_skin:PROD2", "--value", "3"])
    assert out.exit_code == 0, out.output
    doc = json.loads((tmp_path / "neutral" / "hidden_effect.json").read_text())
    assert doc["effect"]["value"] == SYNTHETIC_TRUTH["skin"]  # PROD2's skin as the others'
    assert doc["signal"]["chi2_fit"] < 1e-6 and doc["signal"]["chi2_heldout"] < 1e-6
    again = effect_signal(tmp_path / "neutral" / "case.toml", {**SYNTHETIC_TRUTH, "skin": 5.0})
    assert again["chi2_fit"] > 15  # a different skin everywhere does show ...
    # ... but it is what a global parameter represents: the globals absorb it all
    assert again["chi2_fit_after_globals"] < 0.05 * again["chi2_fit"], again
    assert again["globals_absorbing"]["skin"] < 4.5, again  # from 5 towards the truth's 3
    assert not again["visible_in_fitted_history"]
    if not (PUNQ / "PUNQS3.DATA").is_file():
        pytest.skip(f"PUNQ-S3 data not found at {PUNQ}")
    out = runner.invoke(app, ["hide", "--out", str(tmp_path / "punq"), "--deck",
                              str(PUNQ / "PUNQS3.DATA"), "--candidate",
                              PUNQ_LATE_FAULT[0], "--value", str(PUNQ_LATE_FAULT[1]),
                              "--history-end", str(LATE_FAULT_HISTORY_END), "--record-end",
                              str(PUNQ_RECORD_END), "--seed", "21"])
    assert out.exit_code == 0, out.output
    signal = json.loads((tmp_path / "punq" / "hidden_effect.json").read_text())["signal"]
    assert signal["chi2_fit"] < 15 < signal["chi2_heldout"], signal
    assert not signal["visible_in_fitted_history"]
    assert "the fitted history hardly shows it" in " ".join(out.output.split())


# ============================================================================= slow sweep
SWEEP = [(k, s) for k in KINDS for s in SWEEP_SEEDS] + KNOWN_MISSES


@pytest.mark.slow
@pytest.mark.parametrize("kind,seed", SWEEP, ids=[f"{k}-{s}" for k, s in SWEEP])
def test_sweep_synthetic(tmp_path, kind, seed):
    _opm()
    doc, effect = diagnose_synthetic(tmp_path, kind, seed)
    assert_found_where_visible(doc, effect, tmp_path / "case")


@pytest.mark.slow
@pytest.mark.parametrize("kind", KINDS)
def test_sweep_punq(tmp_path, kind):
    _opm()
    doc, effect = diagnose_punq(tmp_path, kind, 21)
    assert_found_where_visible(doc, effect, tmp_path / "case")


@pytest.mark.slow
@pytest.mark.parametrize("seed", (6, 7))
def test_sweep_controls(tmp_path, seed):
    _opm()
    doc, _ = diagnose_synthetic(tmp_path, None, seed)
    assert doc["causes"][0]["kind"] == "none" and doc["selected"] is None
