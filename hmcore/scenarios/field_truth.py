"""A hidden truth for an ensemble of field models, and the verdict on an ensemble run of it:
what ``hmflow hide --kind field`` and ``hmflow reveal --campaign`` do.

* :func:`draw_truth`: one realisation of a case's own prior (its fields, drawn as
  :func:`hmcore.fields.prior.draw_prior` draws members, and its scalar parameters, uniform in
  their box's scaled coordinates as :func:`hmcore.fields.members.scalar_prior` draws them),
  from a stream no ensemble member of the case uses (see :func:`truth_field_seeds`).
* :func:`hide_field_truth`: write the truth (GRDECL and a one-member ensemble table), run the
  deck with it over the whole schedule (the members' INCLUDE,
  :class:`hmcore.fields.members.MemberSimulator`), and write a new case: the same deck,
  fields, scalars and ``[ensemble]``, its observed history the truth's responses up to the
  case's history end with PUNQ-S3's noise (:func:`hmcore.scenarios.hidden.noisy_history`,
  :data:`hmcore.scoring.noise.PUNQ_NOISE`) and no sigma column, and ``hidden_truth.json``.
* :func:`reveal_field_truth`: from the stored artifacts of an ensemble run
  (:mod:`storage.ensemble`), whether the truth's forecast lies inside the prior's and the
  posterior's P10-P90, and the RMSE of each ensemble's mean field to the truth.

The truth's seed stream: ``SeedSequence(entropy=[the case's ensemble seed, every field's
prior seed], spawn_key=(TRUTH_TAG, seed))`` spawns three children: the fields' seeds, the
scalars and the noise. A field's truth is drawn by ``draw_prior`` with its prior seed replaced
by a 32-bit word of the first child that is none of the case's seeds (nor their low 32 bits),
as member 0; a member ``m`` of the case's ensemble is drawn from ``default_rng([s, m])`` with
``s`` a prior seed. The first word of the truth's entropy thus differs from every member
stream's (and from the ensemble's own ``[seed, i]`` streams), so no member's draw is the
truth's, whatever the ensemble's size.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import tomlkit

from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.grdecl import write_member
from hmcore.fields.grid import FieldGrid, read_grid
from hmcore.fields.layout import Layout
from hmcore.fields.members import MemberSimulator, ensemble_matrix, ensemble_table
from hmcore.fields.prior import draw_prior
from hmcore.fields.spec import FieldSpec, FilesPrior
from hmcore.fields.spread import FieldSpread, field_spread
from hmcore.model.case import Case
from hmcore.simulation.forecast import inside_band
from hmcore.scenarios.hidden import noisy_history
from hmcore.scoring.evaluation import evaluate, simulator_for
from hmcore.scoring.noise import PUNQ_NOISE
from hmcore.simulation.curves import FIELD, read_curves, value_at_end
from hmcore.simulation.forecast import FIELD_QUANTITIES, WELL_QUANTITIES
from storage import ArtifactStore
from storage.ensemble import ENSEMBLE_DOC, ENSEMBLE_FILE, FORECAST_STEP, ensemble_step

FIELD_KIND = "field"
"""``hmflow hide --kind field``."""
TRUTH_TAG = int.from_bytes(b"truth", "big")
"""The spawn key's first word of the truth's seed stream (see the module's docstring)."""
TRUTH_JSON = "hidden_truth.json"
TRUTH_GRDECL = "truth.GRDECL"
TRUTH_TABLE = "truth.parquet"
"""The truth in update space as a one-member ensemble table (:func:`ensemble_table`): what the
truth run's :class:`MemberSimulator` reads, and what ``reveal`` compares the means with."""
TRUTH_RUN = "truth-run"
OBSERVED = "observed.csv"
WORD = 0xFFFFFFFF


@dataclass(frozen=True, eq=False)
class TruthDraw:
    """The truth: ``fields[name]`` ``(n_active,)`` float32 in update space, ``scalars`` their
    scaled coordinates ``(len(layout.scalars),)``, ``field_seeds`` the seeds it was drawn
    with, ``seed`` the request's seed, ``entropy`` the stream's entropy (the case's seeds)."""

    fields: Mapping[str, np.ndarray]
    scalars: np.ndarray
    field_seeds: Mapping[str, int]
    layout: Layout
    seed: int
    entropy: tuple[int, ...]

    @property
    def X(self) -> np.ndarray:
        """The truth as a one-member ensemble ``(1, layout.size)`` float32."""
        return self.layout.stack({n: v[None, :] for n, v in self.fields.items()},
                                 {n: self.scalars[k:k + 1]
                                  for k, n in enumerate(self.layout.scalars)})


def case_seeds(fields: Sequence[FieldSpec], ensemble_seed: int) -> tuple[int, ...]:
    """Every seed an ensemble of the case draws from: ``[ensemble] seed`` (updates, scalars),
    then each drawn field's prior seed."""
    return (int(ensemble_seed), *(int(f.prior.seed) for f in fields
                                  if not isinstance(f.prior, FilesPrior)))


def truth_streams(seeds: Sequence[int], seed: int) -> list[np.random.SeedSequence]:
    """The truth's three streams (fields' seeds, scalars, noise): children of
    ``SeedSequence(seeds, spawn_key=(TRUTH_TAG, seed))``."""
    return np.random.SeedSequence(entropy=list(seeds), spawn_key=(TRUTH_TAG, int(seed))).spawn(3)


def distinct_words(words: Sequence[int], forbidden: set[int], n: int) -> list[int]:
    """The first ``n`` of ``words`` that are not in ``forbidden`` nor repeated; ValueError when
    there are fewer."""
    out: list[int] = []
    for w in (int(x) for x in words):
        if w not in forbidden and w not in out:
            out.append(w)
        if len(out) == n:
            return out
    raise ValueError(f"only {len(out)} of {n} distinct truth seeds among {len(words)} words")


def truth_field_seeds(fields: Sequence[FieldSpec], ensemble_seed: int, seed: int
                      ) -> dict[str, int]:
    """{field: the seed its truth is drawn with}: 32-bit words of the first truth stream,
    none equal to the low 32 bits of a seed of the case (see the module's docstring)."""
    seeds = case_seeds(fields, ensemble_seed)
    forbidden = {s & WORD for s in seeds}
    words = truth_streams(seeds, seed)[0].generate_state(2 * (len(fields) + len(forbidden)) + 8)
    return dict(zip((f.name for f in fields), distinct_words(words, forbidden, len(fields))))


def files_problems(fields: Sequence[FieldSpec]) -> list[str]:
    """A truth is drawn from a stated prior: one line per field whose prior is the user's
    files (a set of realisations, nothing to draw a new one from)."""
    return [f"field '{f.name}': its prior is the user's GRDECL files ({f.prior.folder}), from "
            "which no new realisation can be drawn; hide --kind field needs a drawn prior "
            "(geostatistical, relation or cosimulation)"
            for f in fields if isinstance(f.prior, FilesPrior)]


def draw_truth(fields: Sequence[FieldSpec], grid: FieldGrid, scalars: Sequence[str],
               ensemble_seed: int, seed: int) -> TruthDraw:
    """One realisation of the prior of ``fields`` on ``grid`` and of the ``scalars`` (uniform
    in [-1, 1]), from the truth's streams of ``seed`` (see the module's docstring)."""
    problems = files_problems(fields)
    if problems:
        raise ValueError("; ".join(problems))
    t = truth_field_seeds(fields, ensemble_seed, seed)
    renamed = tuple(f.model_copy(update={"prior": f.prior.model_copy(update={"seed": t[f.name]})})
                    for f in fields)
    drawn = draw_prior(renamed, grid, 1)
    u = np.random.default_rng(truth_streams(case_seeds(fields, ensemble_seed), seed)[1]) \
        .uniform(-1.0, 1.0, len(scalars)).astype(np.float32)
    layout = Layout(tuple(f.name for f in fields), tuple(scalars), grid.n_active)
    return TruthDraw({n: v[0] for n, v in drawn.values.items()}, u, t, layout, int(seed),
                     case_seeds(fields, ensemble_seed))


def field_truth_problems(case: Case) -> list[str]:
    """Every reason ``case`` cannot hide a field truth, one line each ([] when it can)."""
    if not case.fields:
        return [(f"case {case.name} ({case.source}) has no field parameter (kind = \"field\") "
                 "to draw a truth of; hide --kind field needs one (docs/ensembles.md)")]
    return files_problems(case.fields)


def out_problems(out: Path) -> list[str]:
    """``out`` must not exist, or be an empty directory: nothing is ever overwritten."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        return [(f"--out {out}: exists and is not an empty directory; nothing is overwritten, "
                 "choose a new one")]
    return []


@dataclass(frozen=True)
class FieldTruthCase:
    """What :func:`hide_field_truth` wrote."""

    case_toml: Path
    hidden_json: Path
    grdecl: Path
    fopt: float
    observed_rows: int
    history_end_days: float


def hide_field_truth(case: Case, out: Path, seed: int = 0, simulator=None) -> FieldTruthCase:
    """Draw the truth of ``seed`` from ``case``'s prior, run it over the whole schedule and
    write the hidden case into ``out`` (see the module's docstring). ``simulator``: the inner
    simulator of the truth run (default the case's). ValueError for a case or ``out`` that
    :func:`field_truth_problems` / :func:`out_problems` refuse, before anything is drawn or
    run; ValueError when the truth run fails, after removing what was written."""
    out = Path(out)
    problems = out_problems(out) + field_truth_problems(case)
    if problems:
        raise ValueError("; ".join(problems))
    created = not out.exists()
    try:
        return _write(case, out.resolve(), int(seed), simulator)
    except BaseException:
        if created:  # leave nothing half-written behind
            shutil.rmtree(out, ignore_errors=True)
        raise


def _write(case: Case, out: Path, seed: int, simulator) -> FieldTruthCase:
    out.mkdir(parents=True, exist_ok=True)
    grid = read_grid(case.deck)
    truth = draw_truth(case.fields, grid, case.space.names, case.ensemble.seed, seed)
    table = out / TRUTH_TABLE
    ensemble_table(truth.X, truth.layout).to_parquet(table)
    grdecl = write_member(out / TRUTH_GRDECL, case.fields, truth.fields, grid,
                          header=f"hidden truth of {case.source}, seed {seed}")
    whole = Case(**{**case.__dict__, "simulator": case.simulator.model_copy(
        update={"stop_at_last_observation": False})})  # the forecast needs the whole schedule
    runner = MemberSimulator(simulator or simulator_for(whole), table, 0, case.fields, grid,
                             truth.layout, case.info.keyword_names)
    values = case.space.to_values(truth.scalars) if case.space.names else {}
    run_dir = out / TRUTH_RUN
    ev = evaluate(whole, values, run_dir, runner)
    if ev.responses is None:
        raise ValueError(f"the truth run failed ({run_dir}): {ev.reason}")
    wells = sorted(case.observed.well.unique())
    ev.responses.to_csv(out / "truth_responses.csv", index=False)
    end = float(case.history_end_days if case.history_end_days is not None
                else case.observed.days.max())
    noise_rng = np.random.default_rng(truth_streams(truth.entropy, seed)[2])
    obs = noisy_history(ev.responses[ev.responses.well.isin(wells)], noise_rng)
    obs = obs[obs.days <= end + 1e-9].drop(columns=["sigma"])
    obs.to_csv(out / OBSERVED, index=False, float_format="%.6g")
    case_toml = out / "case.toml"
    case_toml.write_text(hidden_case_toml(case, _case_name(out.name), end))
    summary = min(run_dir.glob("*.SMSPEC"))
    forecast = truth_forecast(read_curves(summary, sorted(case.info.wells)),
                              sorted(case.info.wells))
    fopt = next(r["value"] for r in forecast if r["well"] == FIELD and r["quantity"] == "FOPT")
    doc = {"kind": FIELD_KIND, "seed": seed, "case": str(case.source),
           "hidden_case": str(case_toml),
           "seed_stream": {"entropy": list(truth.entropy), "spawn_key": [TRUTH_TAG, seed],
                           "children": "fields' seeds, scalars, noise"},
           "field_seeds": dict(truth.field_seeds),
           "member_seeds": {f.name: f.prior.seed for f in case.fields},
           "scalars": {k: float(v) for k, v in values.items()},
           "fields": [{"name": f.name, "keyword": f.keyword,
                       "space": "log10" if f.in_log else "value"} for f in case.fields],
           "layout": {"fields": list(truth.layout.fields), "scalars": list(truth.layout.scalars),
                      "n_active": truth.layout.n_active},
           "truth_grdecl": str(grdecl), "truth_table": str(table), "truth_run": str(run_dir),
           "summary": str(summary), "history_end_days": end,
           "schedule_end_days": float(case.info.end_days), "observed": str(out / OBSERVED),
           "noise": (f"PUNQ-S3's: BHP {PUNQ_NOISE.bhp_flowing:g} bar flowing / "
                     f"{PUNQ_NOISE.bhp_shut_in:g} bar shut in, GOR {PUNQ_NOISE.gor_before:.0%}"
                     f" / {PUNQ_NOISE.gor_after:.0%} before / after gas breakthrough, WCT "
                     f"{PUNQ_NOISE.wct_before:g} / {PUNQ_NOISE.wct_after:g} before / after "
                     f"water breakthrough, AR(1) rho {PUNQ_NOISE.rho:g}; WOPR exact"),
           "FOPT": fopt, "forecast": forecast}
    hidden_json = out / TRUTH_JSON
    hidden_json.write_text(json.dumps(doc, indent=2) + "\n")
    return FieldTruthCase(case_toml, hidden_json, grdecl, fopt, len(obs), end)


def truth_forecast(curves: pd.DataFrame, wells: Sequence[str]) -> list[dict]:
    """The forecast's quantities at the schedule's end, as the ensemble's forecast has them
    (:func:`hmcore.fields.forecast.member_values`): field FOPT, FWPT, FGPT, each well's WOPT."""
    targets = [(FIELD, q) for q in FIELD_QUANTITIES] + [(w, q) for w in wells
                                                        for q in WELL_QUANTITIES]
    return [{"well": w, "quantity": q, "value": float(value_at_end(curves, w, q))}
            for w, q in targets]


def _case_name(folder: str) -> str:
    name = re.sub(r"[^A-Za-z0-9_.-]", "-", folder).strip("-.")
    return name or "hidden-field"


def hidden_case_toml(case: Case, name: str, history_end_days: float) -> str:
    """The case file of the hidden case: ``case``'s own (comments kept), its ``[case]`` naming
    ``name``, the deck by absolute path, :data:`OBSERVED` beside it and the whole observed
    record fitted (``history_end_days``, its last day)."""
    doc = tomlkit.parse(Path(case.source).read_text())
    section = doc["case"]
    section["name"] = name
    section["deck"] = str(Path(case.deck).resolve())
    section["observed"] = OBSERVED
    section["history_end_days"] = float(history_end_days)
    return tomlkit.dumps(doc)


# ----------------------------------------------------------------------------- reveal
@dataclass(frozen=True)
class QuantityCheck:
    """The truth's value of one forecast quantity against one ensemble's band."""

    ensemble: str
    well: str
    quantity: str
    truth: float
    P90: float
    P50: float
    P10: float
    members: int

    @property
    def inside(self) -> bool:
        """The truth inside [P90, P10] (:func:`hmcore.simulation.forecast.inside_band`)."""
        return inside_band(self.P90, self.P10, self.truth)

    @property
    def width(self) -> float:
        """(P10 - P90) / |P50|: the band's width relative to its centre."""
        return (self.P10 - self.P90) / abs(self.P50) if self.P50 else math.inf


@dataclass(frozen=True)
class FieldReveal:
    """An ensemble run judged against the truth it was run on (:func:`reveal_field_truth`)."""

    campaign: str
    checks: tuple[QuantityCheck, ...]
    errors: tuple[FieldSpread, ...]
    posterior_iteration: int

    def check(self, ensemble: str, well: str, quantity: str) -> QuantityCheck | None:
        return next((c for c in self.checks if (c.ensemble, c.well, c.quantity)
                     == (ensemble, well, quantity)), None)

    @property
    def fopt_inside(self) -> bool:
        """The truth's FOPT inside the posterior's P10-P90."""
        c = self.check("posterior", FIELD, "FOPT")
        return bool(c is not None and c.inside)


def reveal_field_truth(hidden: Path, storage: Path, campaign: str) -> FieldReveal:
    """Judge the ensemble run ``campaign`` in ``storage`` against the truth of ``hidden``
    (a :data:`TRUTH_JSON`), from stored artifacts only: its ``forecast`` (P90/P10 of FOPT,
    FWPT, FGPT and each well's WOPT, prior and posterior: where wells hold their rate control
    the oil is the schedule's and the water and gas tell) and its prior and last ensembles
    (mean fields).
    ValueError (one line) when the file is not a field truth or the run is not there."""
    doc = json.loads(Path(hidden).read_text())
    if doc.get("kind") != FIELD_KIND:
        raise ValueError(f"--hidden {hidden}: not a hidden field truth (written by hmflow hide "
                         "--kind field); a hidden effect is judged with --diagnosis")
    store = ArtifactStore(storage)
    settings = store.settings(campaign)
    if settings is None or settings.get("kind") != "ensemble":
        raise ValueError(f"--campaign {campaign}: no ensemble run of that name in {storage}")
    forecast = store.latest(campaign, FORECAST_STEP)
    if forecast is None:
        raise ValueError(f"--campaign {campaign}: no forecast stored yet (the run has not "
                         "finished; the same hmflow ensemble command resumes it)")
    table = forecast.read_parquet("forecast.parquet")
    checks = []
    for t in doc["forecast"]:  # FOPT, FWPT, FGPT, each well's WOPT
        if not math.isfinite(t["value"]):
            continue
        for e in ("prior", "posterior"):
            row = table[(table.ensemble == e) & (table.well == t["well"])
                        & (table.quantity == t["quantity"])]
            if len(row):
                r = row.iloc[0]
                checks.append(QuantityCheck(e, t["well"], t["quantity"], float(t["value"]),
                                            float(r.P90), float(r.P50), float(r.P10),
                                            int(r.members)))
    last = len(EnsembleSpec.model_validate(settings["ensemble"]).alphas)
    return FieldReveal(campaign, tuple(checks), field_errors(doc, store, campaign, last), last)


def field_errors(doc: dict, store: ArtifactStore, campaign: str, last: int
                 ) -> tuple[FieldSpread, ...]:
    """Per field of the truth: RMSE of the mean of ``ensemble-00`` and of ``ensemble-<last>``
    (members left out, NaN, not counted) to the truth's values, and their spreads."""
    truth_layout = Layout(tuple(doc["layout"]["fields"]), tuple(doc["layout"]["scalars"]),
                          int(doc["layout"]["n_active"]))
    truth = ensemble_matrix(pd.read_parquet(doc["truth_table"]), truth_layout)[0]
    spaces = {f["name"]: f["space"] for f in doc["fields"]}
    ensembles = []
    for i in (0, last):
        version = store.latest(campaign, ensemble_step(i))
        if version is None:
            raise ValueError(f"--campaign {campaign}: {ensemble_step(i)} is not stored")
        meta = version.read_json(ENSEMBLE_DOC)
        layout = Layout(tuple(meta["fields"]), tuple(meta["scalars"]), int(meta["n_active"]))
        if layout.fields != truth_layout.fields or layout.n_active != truth_layout.n_active:
            raise ValueError(f"--campaign {campaign}: its fields {list(layout.fields)} on "
                             f"{layout.n_active} cells are not the truth's "
                             f"{list(truth_layout.fields)} on {truth_layout.n_active}")
        ensembles.append(ensemble_matrix(version.read_parquet(ENSEMBLE_FILE), layout))
    out = []
    for name in truth_layout.fields:
        cols = truth_layout.columns(name)
        out.append(field_spread(name, ensembles[0][:, cols], ensembles[1][:, cols],
                                truth[cols], spaces.get(name, "")))
    return tuple(out)
