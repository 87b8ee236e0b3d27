"""Cases with a hidden effect: the "measured" data come from a truth that has one extension
the calibration space lacks (:mod:`hmcore.scenarios.effects`, drawn by
:mod:`hmcore.scenarios.generators`). Used by ``hmflow hide``, the tests and the benchmark of the
diagnosis; :mod:`hmcore.scenarios.judge` scores an answer against the truth.

* :func:`write_hidden_synthetic_case` writes the built-in synthetic case (seeded fields, noise
  and the known global truth) with the effect applied in the truth run, through
  :func:`hmcore.scenarios.synthetic.write_synthetic_case` (``truth_space`` = reference + the effect).
* :func:`write_hidden_deck_case` does the same for any deck (e.g. PUNQ-S3): a truth run of the
  deck with the effect applied by :func:`hmcore.model.run_deck.prepare_run_deck`, PUNQ-style noise
  (BHP 3 bar flowing / 1 bar shut in, GOR 10 % / 25 % of the value before / after gas
  breakthrough, WCT 0.02 / 0.05 before / after water breakthrough, AR(1) in time), an
  observed CSV (optionally without sigma) and a case TOML.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.scoring.observations import ObservationSet
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.model.case import default_history_end, load_case_file
from hmcore.model.run_deck import prepare_run_deck
from hmcore.diagnosis.recalibrate import (Coordinates, LevenbergMarquardt, LMSettings, Point,
                                         run_lockstep)
from hmcore.model.parameters import ParameterSpace
from hmcore.scenarios.effects import HiddenEffect
from hmcore.scenarios.generators import draw_effects
from hmcore.scenarios.synthetic import (DECK_NAME, SYNTHETIC_TRUTH, noisy_series, write_synthetic_case)
from hmcore.scenarios.synthetic_deck import make_fields, render_deck
from hmcore.scoring.noise import PUNQ_NOISE, NoiseModel
from hmcore.scoring.evaluation import evaluate, score_responses
from hmcore.simulation.responses import read_responses
from hmcore.simulation.simulator import OpmFlow


def _effects_json(effects: list[HiddenEffect], truth: dict, signal: dict | None,
                  kind: str | None = None) -> str:
    return json.dumps({"kind": kind, "effect": effects[0].to_dict() if effects else None,
                       "effects": [e.to_dict() for e in effects], "truth": truth,
                       "signal": signal}, indent=2) + "\n"


# ----------------------------------------------------------------------------- synthetic case
def synthetic_deck_info(seed: int, directory: Path | None = None) -> DeckInfo:
    """DeckInfo of the synthetic base deck of ``seed``, written into ``directory`` (default: a
    new temporary directory, left in place since the DeckInfo points at the file)."""
    field_rng, _ = np.random.default_rng(seed).spawn(2)
    directory = Path(directory or tempfile.mkdtemp(prefix="hmflow-hidden-deck-"))
    directory.mkdir(parents=True, exist_ok=True)
    deck = directory / DECK_NAME
    deck.write_text(render_deck(make_fields(field_rng), seed))
    return DeckInfo.inspect(deck)


def write_hidden_synthetic_case(dest: Path, seed: int, kind: str | None = None,
                                effect: HiddenEffect | None = None,
                                history_end_days: float | None = None
                                ) -> tuple[Path, HiddenEffect | None]:
    """The synthetic case of ``seed`` whose truth hides ``effect`` (or those drawn of ``kind``:
    a library kind or a generator; neither: the control, nothing hidden). Returns (case.toml,
    the first effect); every effect is written to ``dest/hidden_effect.json``."""
    space = ParameterSpace.reference()
    effects = [effect] if effect is not None else []
    if effect is None and kind is not None:
        info = synthetic_deck_info(seed, Path(dest) / "base-deck")
        effects = draw_effects(kind, seed, info, space, SYNTHETIC_TRUTH)
    hidden = {e.parameter.name: e.value for e in effects}
    if not effects:
        case = write_synthetic_case(dest, seed, history_end_days=history_end_days)
    else:
        truth_space = ParameterSpace(parameters=space.parameters
                                     + tuple(e.parameter for e in effects))
        case = write_synthetic_case(dest, seed, truth=hidden, truth_space=truth_space,
                                    history_end_days=history_end_days)
    truth = {**SYNTHETIC_TRUTH, **hidden}
    signal = effect_signal(case, SYNTHETIC_TRUTH) if effects else None
    (Path(dest) / "hidden_effect.json").write_text(_effects_json(effects, truth, signal, kind))
    return case, (effects[0] if effects else None)


# ----------------------------------------------------------------------------- any deck
def noisy_history(truth: pd.DataFrame, rng: np.random.Generator,
                  noise: NoiseModel = PUNQ_NOISE, start_day: float = 0.5) -> pd.DataFrame:
    """Observed rows (well, days, quantity, value, sigma, flowing) from noise-free responses
    (WOPR, WBHP, WGOR, WWCT per well), with the noise of :func:`hmcore.scenarios.synthetic.noisy_series`.

    WOPR: the rate control, exact, no sigma. WBHP, WGOR (flowing), WWCT (flowing): the truth
    plus sigma times a unit AR(1) series along each well's rows.
    """
    wide = truth[truth.days >= start_day].pivot_table(index=["well", "days"], columns="quantity",
                                                      values="value")
    rows = []
    for well in sorted(wide.index.get_level_values("well").unique()):
        t = wide.loc[well]
        series, _, _ = noisy_series(t.index.to_numpy(float), t["WOPR"].to_numpy(),
                                    t["WBHP"].to_numpy(), t["WGOR"].to_numpy(),
                                    t["WWCT"].to_numpy(), rng, noise)
        rows += [pd.DataFrame({"well": well, "days": x.days, "quantity": x.quantity,
                               "value": x.value, "sigma": x.sigma,
                               "flowing": x.flowing.astype(int)})
                 for x in series if x.days.size or x.quantity in ("WOPR", "WBHP")]
    obs = pd.DataFrame(pd.concat(rows, ignore_index=True))
    obs["value"] = obs["value"] + 0.0
    return obs


def write_hidden_deck_case(dest: Path, deck: Path, seed: int, *, truth: dict[str, float],
                           space: ParameterSpace | None = None, kind: str | None = None,
                           effect: HiddenEffect | None = None,
                           history_end_days: float | None = None, with_sigma: bool = True, name: str = "hidden",
                           end_days: float | None = None,
                           simulator=None) -> tuple[Path, HiddenEffect | None]:
    """A case on ``deck`` whose measured data hide ``effect`` (or one drawn of ``kind``).

    ``truth``: values of the calibration ``space`` (default: the reference five) in the truth.
    Writes ``observed.csv``, ``truth_responses.csv``, ``hidden_effect.json`` and ``case.toml``
    (deck given by absolute path) into ``dest``; returns (case.toml, effect). ``end_days``
    ends the measured record (default: the end of the schedule); ``history_end_days`` ends
    the fitted history (default: 75 % of the record).
    """
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    deck = Path(deck).resolve()
    info = DeckInfo.inspect(deck)
    if history_end_days is None:
        history_end_days = round(default_history_end(
            0.0, info.end_days if end_days is None else end_days))
    space = space or ParameterSpace.reference()
    effects = [effect] if effect is not None else []
    if effect is None and kind is not None:
        effects = draw_effects(kind, seed, info, space, truth)
    truth_space = ParameterSpace(parameters=space.parameters
                                 + tuple(e.parameter for e in effects))
    values = {**truth, **{e.parameter.name: e.value for e in effects}}
    sim = simulator or OpmFlow()
    run_dir = dest / "truth-run"
    run_deck = prepare_run_deck(deck, values, truth_space, run_dir, info)
    result = sim.run(run_deck, run_dir)
    truth_df = read_responses(result.summary_path, sorted(info.wells))
    truth_df.to_csv(dest / "truth_responses.csv", index=False)
    obs = noisy_history(truth_df, np.random.default_rng([seed, 7919]))
    if end_days is not None:
        obs = obs[obs.days <= end_days + 1e-9]
    if not with_sigma:
        obs = obs.drop(columns=["sigma"])
    obs.to_csv(dest / "observed.csv", index=False, float_format="%.6g")
    case = dest / "case.toml"
    case.write_text(f'[case]\nname = "{name}"\ndeck = "{deck}"\nobserved = "observed.csv"\n'
                    f"history_end_days = {history_end_days:g}\n")
    signal = effect_signal(case, truth, sim) if effects else None
    (dest / "hidden_effect.json").write_text(_effects_json(effects, values, signal, kind))
    return case, (effects[0] if effects else None)


SIGNAL_VISIBLE = DiagnosisSettings().chi2_threshold
"""Chi-square of a hidden effect's signal on the fitted history under which a diagnosis cannot
be expected to name it: the score test's line of a full search (:class:`DiagnosisSettings`,
``false_alarm`` over :data:`hmcore.diagnosis.settings.DEFAULT_TESTS` candidates)."""


def effect_signal(case_toml: Path, truth_globals: dict[str, float], simulator=None, *,
                  absorbed: bool = True, workers: int = 2,
                  settings: LMSettings | None = None) -> dict:
    """How strongly the hidden effect shows in the measured history of the case ``case_toml``.

    The truth without the effect (``truth_globals``: the calibration parameters' true values,
    one simulator run) against the truth with it (``truth_responses.csv`` beside the case),
    standardised and whitened under the noise model the diagnosis arrives at when its five
    parameters are right (sigma from the CSV or estimated, and the AR(1) time correlation,
    from the residuals of the run without the effect: the noise plus what the effect leaves,
    as the diagnosis sees them): ``chi2_fit`` and
    ``chi2_heldout`` are the sums of squares of that difference on the fitted and the held-back
    history (``n_fit``, ``n_heldout`` points).

    The global parameters can absorb part of the effect (a layer's permeability is partly a
    global permeability multiplier). With ``absorbed`` (and ``chi2_fit`` at the line or above),
    the base model's globals are fitted to the noiseless truth - bounded Levenberg-Marquardt on
    the whitened fitted-history difference from ``truth_globals``, ``workers`` runs at a time,
    about 20 runs - and ``chi2_fit_after_globals`` is what remains: the expected chi-square
    gain of the right extension over the best five-parameter fit (the non-centrality of the
    test that names it); ``chi2_heldout_after_globals`` is that best fit's error on the
    held-back history, ``globals_absorbing`` its values. ``visible_in_fitted_history`` is
    whether what remains reaches :data:`SIGNAL_VISIBLE`. ``truth_E`` and ``truth_E_heldout``
    are the truth's own misfit E against the noisy history (no run): a diagnosis cannot be
    asked to bring the held-back E below what the truth scores (see :func:`judge`)."""
    case = load_case_file(case_toml)
    folder = Path(case_toml).parent
    truth = pd.read_csv(folder / "truth_responses.csv")
    obs = ObservationSet.from_case(case)
    names = case.space.names
    with tempfile.TemporaryDirectory(prefix="effect-signal-", dir=folder) as tmp:
        counter = iter(range(10**9))

        def simulate(values: dict[str, float]):
            run_dir = Path(tmp) / f"run{next(counter)}"
            res = evaluate(case, values, run_dir, simulator)
            shutil.rmtree(run_dir, ignore_errors=True)  # the responses are in memory
            return res

        start = {n: float(truth_globals[n]) for n in names}
        without = simulate(start)
        if without.responses is None:
            return {"error": f"the truth without the effect failed to simulate: "
                             f"{without.reason}"}
        # the noise model the diagnosis arrives at when its five parameters are right: sigma
        # (where the CSV gives none) and its time correlation estimated from the residuals of
        # the model without the effect, which carry the noise and what the effect leaves
        obs = obs.refine(without.responses, case.observed)
        z_truth = obs.standardized(truth)

        def difference(values: dict[str, float]) -> tuple[np.ndarray | None, str]:
            """Standardised base model at ``values`` minus the truth (None: the run failed)."""
            res = without if values == start else simulate(values)
            if res.responses is None:
                return None, str(res.reason)
            return obs.standardized(res.responses) - z_truth, ""

        d, reason = difference(start)
        fit, held = obs.whiten(d, "fit"), obs.whiten(d, "heldout")
        chi2_fit, chi2_held = float(fit @ fit), float(held @ held)
        truth_score = score_responses(case, truth)
        out = {"truth_E": truth_score["E"], "truth_E_heldout": truth_score["E_heldout"],
               "chi2_fit": chi2_fit, "chi2_heldout": chi2_held, "n_fit": int(fit.size),
               "n_heldout": int(held.size), "n_heldout_measured": obs.n_noise("heldout"),
               "history_end_days": obs.history_end_days}
        remains = chi2_fit
        if absorbed and chi2_fit >= SIGNAL_VISIBLE:
            coords = Coordinates(case.space.parameters)
            u0 = coords.to_u(start)
            lm = LevenbergMarquardt(u0, settings or LMSettings(
                fd_step=0.1, max_iter=6, max_evaluations=24, trials=2, ftol=0.01),
                start=Point(u0, fit, held), label="globals absorbing the effect")

            def evaluate_batch(batch):
                with ThreadPoolExecutor(max(workers, 1)) as pool:
                    diffs = list(pool.map(lambda b: difference(coords.to_values(b[1]))[0],
                                          batch))
                return [(None, None) if x is None else (obs.whiten(x, "fit"),
                                                        obs.whiten(x, "heldout"))
                        for x in diffs]

            run_lockstep([lm], evaluate_batch, workers)
            best = lm.best
            remains = best.ssr
            out.update({"chi2_fit_after_globals": remains,
                        "chi2_heldout_after_globals": float(best.payload @ best.payload),
                        "globals_absorbing": coords.to_values(best.u),
                        "absorbing_runs": lm.n_evaluations})
    out["visible_in_fitted_history"] = bool(remains >= SIGNAL_VISIBLE)
    return out


