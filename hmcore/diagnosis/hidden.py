"""Cases with a hidden effect: the "measured" data come from a truth that has one extension
the calibration space lacks. Used by the tests and the benchmark of the diagnosis.

* :func:`draw_effect` draws, from a seed, one library candidate of a kind (which well, layer,
  fault plane, aquifer, table) and a strength within realistic ranges.
* :func:`write_hidden_synthetic_case` writes the built-in synthetic case (seeded fields, noise
  and the known global truth) with the effect applied in the truth run, through
  :func:`hmcore.synthetic.write_synthetic_case` (``truth_space`` = reference + the effect).
* :func:`write_hidden_deck_case` does the same for any deck (e.g. PUNQ-S3): a truth run of the
  deck with the effect applied by :func:`hmcore.deck.prepare_run_deck`, PUNQ-style noise
  (BHP 3 bar flowing / 1 bar shut in, GOR 10 % / 25 % of the value before / after gas
  breakthrough, WCT 0.02 / 0.05 before / after water breakthrough, AR(1) in time), an
  observed CSV (optionally without sigma) and a case TOML.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from hmcore.deck_info import DeckInfo
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.diagnosis.extensions import KINDS, Candidate, build_candidates
from hmcore.diagnosis.recalibrate import (Coordinates, LevenbergMarquardt, LMSettings, Point,
                                         run_lockstep)
from hmcore.parameters import Parameter, ParameterSpace
from hmcore.synthetic import PUNQ_NOISE, NoiseModel, noisy_series

STRENGTH = {
    # kind: ((low, high) of a decrease, (low, high) of an increase, P(decrease)); factors or
    # skin increments (well_skin) / exponents (relative_permeability)
    "well_skin": ((-6.0, -4.0), (8.0, 15.0), 0.25),
    "regional_permeability": ((0.15, 0.35), (3.0, 6.0), 0.6),
    "layer_permeability": ((0.15, 0.3), (3.0, 5.0), 0.5),
    "vertical_permeability": ((0.001, 0.01), (30.0, 100.0), 1.0),
    "aquifer_strength": ((0.03, 0.12), (5.0, 15.0), 0.5),
    "fault_transmissibility": ((1e-3, 1e-2), (1e-3, 1e-2), 1.0),
    "relative_permeability": ((0.4, 0.55), (2.2, 2.9), 0.5),
}
"""Realistic ranges of hidden effects, log-uniform for multipliers. Vertical permeability is
drawn as a baffle (kv cut 100-1000 times): raising kv changes nothing once it is not the
bottleneck. An aquifer productivity index is drawn weaker (see :data:`STRENGTH_OVERRIDES`)."""

STRENGTH_OVERRIDES = {"aquifer_strength:AQUFETP:6": ((0.005, 0.03), (0.005, 0.03), 1.0),
                      "relative_permeability:water:endpoint": ((-0.10, -0.05), (0.05, 0.10), 0.5),
                      "relative_permeability:gas:endpoint": ((-0.10, -0.05), (0.05, 0.10), 0.5)}
"""Per-candidate ranges (id prefix): a Fetkovich aquifer's productivity index matters only
when it, not the grid, limits the influx, i.e. when it is much weaker than the deck's; a
critical-saturation shift is a saturation change (uniform, added), not a factor."""


@dataclass(frozen=True)
class HiddenEffect:
    """One hidden extension: the library candidate and its true value."""

    candidate: Candidate
    value: float

    @property
    def kind(self) -> str:
        return self.candidate.kind

    @property
    def parameter(self) -> Parameter:
        return self.candidate.parameter

    def to_dict(self) -> dict:
        return {"id": self.candidate.id, "kind": self.kind, "wells": list(self.candidate.wells),
                "layers": list(self.candidate.layers), "value": self.value,
                "parameter": self.parameter.model_dump(mode="json"),
                "description": self.candidate.description,
                "generated": self.candidate.details.get("generated"),
                "expect_wells": self.candidate.details.get("expect_wells") or [],
                "expect_ids": self.candidate.details.get("expect_ids") or [],
                "start_day": self.candidate.details.get("start_day")}

    @property
    def generated(self) -> str | None:
        """The generator that made it (:mod:`hmcore.diagnosis.generators`), None for a
        library candidate."""
        return self.candidate.details.get("generated")


def chosen_effect(candidate_id: str, value: float, info: DeckInfo, space: ParameterSpace,
                  values: dict[str, float]) -> HiddenEffect:
    """The library candidate ``candidate_id`` (see :func:`build_candidates`) at ``value``.

    Raises ValueError naming the known ids of the kind, or the bounds the value breaks."""
    kind = candidate_id.split(":", 1)[0]
    if kind not in KINDS:
        raise ValueError(f"candidate id {candidate_id!r} must start with a kind of {list(KINDS)}"
                         ", e.g. 'well_skin:PROD2'")
    cands = build_candidates(info, space, values, (kind,))
    c = next((c for c in cands if c.id == candidate_id), None)
    if c is None:
        raise ValueError(f"the deck {info.path} offers no candidate {candidate_id!r}; its "
                         f"{kind} candidates are {[c.id for c in cands]}")
    p = c.parameter
    if not p.low <= value <= p.high:
        raise ValueError(f"{candidate_id}: low <= value <= high must hold, got value={value:g}, "
                         f"low={p.low:g}, high={p.high:g}")
    return HiddenEffect(c, float(value))


def _effect_of(e: dict) -> HiddenEffect:
    details = {"generated": e["generated"], "expect_wells": e.get("expect_wells") or [],
               "expect_ids": e.get("expect_ids") or []} if e.get("generated") else {}
    if e.get("start_day") is not None:
        details["start_day"] = float(e["start_day"])
    c = Candidate(id=e["id"], kind=e["kind"], parameter=Parameter.model_validate(e["parameter"]),
                  wells=tuple(e.get("wells", ())), layers=tuple(e.get("layers", ())),
                  description=e.get("description", ""), details=details)
    return HiddenEffect(c, float(e["value"]))


def load_hidden_effects(path: Path) -> list[HiddenEffect]:
    """Every effect a ``hidden_effect.json`` (written by the ``write_hidden_*`` functions)
    describes; empty for a control."""
    doc = json.loads(Path(path).read_text())
    if isinstance(doc, dict) and "effects" in doc:
        return [_effect_of(e) for e in doc["effects"]]
    e = doc.get("effect") if isinstance(doc, dict) and "truth" in doc else doc
    return [] if e is None else [_effect_of(e)]


def load_hidden_effect(path: Path) -> HiddenEffect | None:
    """The (first) effect a ``hidden_effect.json`` describes; None for a control."""
    effects = load_hidden_effects(path)
    return effects[0] if effects else None


def draw_effects(kind: str, seed: int, info: DeckInfo, space: ParameterSpace,
                 values: dict[str, float]) -> list[HiddenEffect]:
    """The effects of ``kind``: a library kind (one candidate, :func:`draw_effect`) or a
    generator of :mod:`hmcore.diagnosis.generators`."""
    from hmcore.diagnosis.generators import GENERATORS, generate

    if kind in GENERATORS:
        return generate(kind, seed, info, space, values)
    return [draw_effect(kind, seed, info, space, values)]


def _effects_json(effects: list[HiddenEffect], truth: dict, signal: dict | None,
                  kind: str | None = None) -> str:
    return json.dumps({"kind": kind, "effect": effects[0].to_dict() if effects else None,
                       "effects": [e.to_dict() for e in effects], "truth": truth,
                       "signal": signal}, indent=2) + "\n"


def draw_effect(kind: str, seed: int, info: DeckInfo, space: ParameterSpace,
                values: dict[str, float], choices: list[str] | None = None) -> HiddenEffect:
    """A random candidate of ``kind`` (optionally among ids ``choices``) and strength."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}")
    if kind == "productivity_change":  # dated by the diagnosis: drawn as by its generator
        from hmcore.diagnosis.generators import generate

        return generate("dated_productivity", seed, info, space, values)[0]
    rng = np.random.default_rng([seed, KINDS.index(kind)])
    every = build_candidates(info, space, values, (kind,))
    cands = [c for c in every if choices is None or c.id in choices]
    if not cands:
        raise ValueError(f"the deck {info.path} offers no {kind} candidate"
                         + (f" among {choices}; its {kind} candidates are "
                            f"{[c.id for c in every]}" if choices is not None else ""))
    c = cands[int(rng.integers(len(cands)))]
    spec = next((v for k, v in STRENGTH_OVERRIDES.items() if c.id.startswith(k)), STRENGTH[kind])
    (dlo, dhi), (ulo, uhi), p_down = spec
    lo, hi = (dlo, dhi) if rng.random() < p_down else (ulo, uhi)
    if kind == "well_skin":
        value = c.neutral + float(rng.uniform(lo, hi))
    elif c.parameter.mode == "endpoint":  # a shift; none below a table's first row
        value = c.neutral + float(rng.uniform(lo, hi))
        value = -value if value < c.parameter.low else value
    else:
        value = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    value = float(np.clip(value, c.parameter.low, c.parameter.high))
    return HiddenEffect(c, value)


# ----------------------------------------------------------------------------- synthetic case
def synthetic_deck_info(seed: int, directory: Path | None = None) -> DeckInfo:
    """DeckInfo of the synthetic base deck of ``seed``, written into ``directory`` (default: a
    new temporary directory, left in place since the DeckInfo points at the file)."""
    from hmcore.synthetic import DECK_NAME, make_fields, render_deck

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
    from hmcore.synthetic import SYNTHETIC_TRUTH, write_synthetic_case

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
    (WOPR, WBHP, WGOR, WWCT per well), with the noise of :func:`hmcore.synthetic.noisy_series`.

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
    from hmcore.deck import prepare_run_deck
    from hmcore.responses import read_responses
    from hmcore.simulator import OpmFlow

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    deck = Path(deck).resolve()
    info = DeckInfo.inspect(deck)
    if history_end_days is None:
        history_end_days = round(0.75 * (info.end_days if end_days is None else end_days))
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
    from hmcore.case import load_case
    from hmcore.diagnosis.residuals import ObservationSet
    from hmcore.evaluation import evaluate, score_responses

    case = load_case(case_toml)
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


# ----------------------------------------------------------------------------- scoring a finding
def visible(signal: dict | None) -> bool:
    """Can a diagnosis be asked to find the effect whose :func:`effect_signal` is ``signal``?
    When it shows in the fitted history beyond the score test's line once the globals absorb
    what they can (``visible_in_fitted_history``), or when it shows in the held-back history
    beyond the diagnosis's own held-back noise line (what the globals leave there, or all of it
    when the fitted history shows nothing for them to absorb): the calibrated model then
    misses the held-back history and the diagnosis takes the longer record (an effect that
    starts after the fitted window). No signal: visible (nothing says otherwise)."""
    from hmcore.diagnosis.decision import heldout_decisive_drop

    s = signal or {}
    if s.get("visible_in_fitted_history", True):
        return True
    held = s.get("chi2_heldout_after_globals", s.get("chi2_heldout"))
    n = s.get("n_heldout_measured")
    return bool(held is not None and n and
                held >= heldout_decisive_drop(int(n), DiagnosisSettings()))


BOX_AGREEMENT = 0.25
"""Least Jaccard index (columns in both boxes over columns in either) at which a named region
is the hidden one (:func:`boxes_agree`)."""


def boxes_agree(a, b) -> bool:
    """Do two boxes of columns (i0, i1, j0, j1, ...; 1-based, inclusive) lie in the same
    place: do they share at least :data:`BOX_AGREEMENT` of the columns either covers? A 7x7
    box holding a 5x5 one (0.51), one moved 3 cells along one axis (0.40) or a 7x7 box sharing
    4 x 4 columns with a 5x5 one (0.28) do; a 7x7 box moved 3 cells along both axes (0.20), or
    centred on a well while a 9x9 one is centred 3 cells off it in i and j (0.24), do not. With
    a handful of wells the data locate a region to a few cells, not to the cell."""
    if a is None or b is None:
        return False
    di = min(a[1], b[1]) - max(a[0], b[0]) + 1
    dj = min(a[3], b[3]) - max(a[2], b[2]) + 1
    shared = max(di, 0) * max(dj, 0)
    size = lambda x: (x[1] - x[0] + 1) * (x[3] - x[2] + 1)  # noqa: E731
    return shared >= BOX_AGREEMENT * (size(a) + size(b) - shared)


def _box(cause: dict):
    """The box of a cause (its parameter's, in the cause's ``machine`` record)."""
    return (((cause.get("machine") or {}).get("parameter") or {}).get("box")
            or cause.get("box"))


def described(cause: dict, doc: dict) -> dict:
    """``cause`` with its ``machine`` record, from the diagnosis's ranked causes when it has
    none (an accepted or selected cause carries its id, not its parameter)."""
    if cause.get("machine"):
        return cause
    ranked = next((c for c in doc.get("causes") or [] if c.get("id") == cause.get("id")), {})
    return {**cause, "machine": ranked.get("machine")}


def names(cause: dict, effect: HiddenEffect) -> bool:
    """Does ``cause`` (a ranked or accepted cause of a diagnosis) name ``effect``? Its kind,
    and where the kind names one, the same well (well skin), place (regional permeability: the
    two boxes overlap, :func:`boxes_agree` - the ranking also tries boxes moved beside a well,
    so a well's name alone does not say where), layer (layer and vertical
    permeability) or candidate (fault plane, aquifer item, relperm table). A generated effect
    (:mod:`hmcore.diagnosis.generators`), which no candidate matches exactly: its family,
    naming the wells it expects (``expect_wells``) and, where it lists them, being one of
    ``expect_ids`` (a partial fault: the library plane that parts the producers the same way),
    or for a region, its box as above."""
    h = effect.candidate
    if cause["kind"] != h.kind:
        return False
    start = h.details.get("start_day")
    if start is not None:  # a dated effect: the cause's start date too
        from hmcore.diagnosis.generators import START_TOLERANCE_DAYS

        got = cause.get("start_day")
        if got is None or abs(float(got) - float(start)) > START_TOLERANCE_DAYS:
            return False
    if h.kind == "regional_permeability":  # where the box lies, not which well labels it
        return boxes_agree(_box(cause), h.parameter.box)
    if effect.generated:
        ids = h.details.get("expect_ids")
        return set(h.details.get("expect_wells") or []) <= set(cause["wells"]) and \
            (not ids or cause["id"] in ids)
    if h.kind == "well_skin":
        return cause["wells"] == list(h.wells)
    if h.kind in ("layer_permeability", "vertical_permeability"):
        return cause["layers"] == list(h.layers)
    return cause["id"] == h.id


def judge_effects(doc: dict, effects: list[HiddenEffect], signal: dict | None = None) -> dict:
    """Did the diagnosis ``doc`` find every hidden effect? One library effect (or none): as
    :func:`judge`. Otherwise each effect must be named (:func:`names`) by an accepted cause -
    an effect of no family (kind ``unexplained``) by the first cause - and, unless all are of
    no family, the held-back misfit must drop as in :func:`judge`. Returns ``found``,
    ``named`` (effect id -> bool), ``heldout_improved``, the ranking and the verdict."""
    if len(effects) <= 1 and not (effects and effects[0].generated):
        return judge(doc, effects[0] if effects else None, signal)
    accepted = doc.get("accepted") or ([doc["selected"]] if doc.get("selected") else [])
    first = doc["causes"][0]
    # an effect of no family the data hardly show: `none` is right too
    invisible = not visible(signal)
    no_family = ("unexplained", "none") if invisible else ("unexplained",)
    named = {e.candidate.id: (first["kind"] in no_family if e.kind == "unexplained"
                              else any(names(described(a, doc), e) for a in accepted))
             for e in effects}
    g = doc["gain"]
    held = g["heldout_after"] is not None and g["heldout_before"] is not None and \
        g["heldout_after"] < g["heldout_before"]
    truth_e = (signal or {}).get("truth_E_heldout")
    if not held and truth_e is not None and g["heldout_before"] is not None and \
            truth_e >= g["heldout_before"]:
        held = g.get("ssr_heldout_after") is not None and \
            g["ssr_heldout_after"] < g["ssr_heldout_before"]
    need_held = any(e.kind != "unexplained" for e in effects)
    top = [f"{c['id']} ({c['chi2']:.0f})" for c in doc["causes"][:4] if c["chi2"] is not None]
    return {"hidden": [e.candidate.id for e in effects], "named": named,
            "accepted": [a["id"] for a in accepted], "heldout_improved": bool(held),
            "found": bool(all(named.values()) and (held or not need_held)),
            "ranking": top, "verdict": doc["verdict"],
            "gain": {k: g[k] for k in ("fit_before", "fit_after", "heldout_before",
                                       "heldout_after")}}


def judge(doc: dict, effect: HiddenEffect | None, signal: dict | None = None) -> dict:
    """Did the diagnosis ``doc`` find the hidden ``effect`` (None: the control)?

    ``ranked_first``: the first cause has the hidden kind and, where the kind names one, the
    same well (well skin, regional permeability), layer (layer and vertical permeability) or
    candidate (fault plane, aquifer item, relperm table); ``selected``: the same candidate was
    accepted; ``heldout_improved``: the held-back misfit E (the issue's measure of the gain)
    went down - or, when the truth itself scores a held-back E no better than the calibrated
    base model (``signal["truth_E_heldout"]``, from :func:`effect_signal`: the noise decides E
    there, no diagnosis can lower it with the right answer), the noise-weighted held-back misfit
    (whitened SSR) went down; ``heldout_E_improved`` says what E did. For the control all
    three mean "reported none". ``found`` = all three.
    """
    first = doc["causes"][0]
    if doc.get("lead") and first["kind"] == "unexplained" and len(doc["causes"]) > 1:
        first = doc["causes"][1]  # a partial answer: as judge_effects, by what was accepted
    top = [f"{c['id']} ({c['chi2']:.0f})" for c in doc["causes"][:4] if c["chi2"] is not None]
    g = doc["gain"]
    if effect is None:
        ok = first["kind"] == "none" and doc["selected"] is None
        return {"hidden": None, "ranked_first": ok, "selected": ok, "heldout_improved": ok,
                "found": ok, "ranking": top, "verdict": doc["verdict"]}
    h = effect.candidate
    same = names(first, effect)
    sel = doc["selected"] is not None and (  # the same candidate, or for a region the place
        doc["selected"]["id"] == h.id or (h.kind == "regional_permeability"
                                          and names(described(doc["selected"], doc), effect)))
    held_e = (g["heldout_after"] is not None and g["heldout_before"] is not None
              and g["heldout_after"] < g["heldout_before"])
    truth_e = (signal or {}).get("truth_E_heldout")
    e_cannot_tell = (truth_e is not None and g["heldout_before"] is not None
                     and truth_e >= g["heldout_before"])
    held = held_e or (e_cannot_tell and g.get("ssr_heldout_after") is not None
                      and g["ssr_heldout_after"] < g["ssr_heldout_before"])
    return {"hidden": h.id, "value": effect.value, "ranked_first": bool(same),
            "selected": bool(sel), "heldout_improved": bool(held),
            "heldout_E_improved": bool(held_e), "truth_E_heldout": truth_e,
            "found": bool(same and sel and held), "ranking": top, "verdict": doc["verdict"],
            "gain": {k: g[k] for k in ("fit_before", "fit_after", "heldout_before",
                                       "heldout_after")}}
