"""Sensitivity screening (``hmflow screen``): which parameters move which responses.

Three methods, the designs and estimators of the last two from SALib (never written here):

* ``oat``: one at a time from the prior centre (the middle of the box in the case's own scaling,
  log-aware), or from the deck's own values (``--centre deck``): the centre, then each parameter alone to its low and its high bound; 2d + 1
  calls. Its importance is the *swing* ``|y(high) - y(low)|``, drawn as a tornado.
* ``morris``: elementary effects (``SALib.sample.morris`` / ``SALib.analyze.morris``), ``r``
  trajectories of d + 1 points on :data:`MORRIS_LEVELS` levels, ``r = budget // (d + 1)``;
  importance ``mu*`` (mean absolute elementary effect), with ``sigma``.
* ``sobol``: Sobol' indices (``SALib.sample.sobol``, Saltelli's scheme without second order, and
  ``SALib.analyze.sobol``), N(d + 2) points with N the largest power of two the budget allows
  (at least :data:`SOBOL_MIN_N`); importance the total index ``ST``, with ``S1`` and their
  confidence half-widths.

Every design is drawn in the unit box and mapped to parameter values through the case's
:class:`~hmcore.model.parameters.ParameterSpace` (``u = 2x - 1``, its bounds and log flags).
Randomness is a ``numpy.random.default_rng(seed)`` passed to SALib, never a global seed.

The responses of a call (:func:`responses_of`) are read from its journaled record: per well and
quantity the whitened misfit contribution over the fitted history (mean squared whitened
residual, as the least-squares fit weighs it) and the simulated value at the history end; and
the overall ``objective`` (the case's: the likelihood chi2/n, or E) and ``E``.

The rule (:data:`SWITCH_ON_SHARE`): a parameter matters when its importance on the case's
objective is at least a tenth of the largest parameter's. Importances are effects on one
scale (one response), so the ratio is free of units; a parameter under a tenth of the strongest
moves the misfit by less than a tenth of what the strongest does over the same box, which a
match fitting the strongest cannot resolve reliably, and freeing it costs calls in every
later campaign.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import pandas as pd
from SALib.analyze import morris as morris_analyze
from SALib.analyze import sobol as sobol_analyze
from SALib.sample import morris as morris_sample
from SALib.sample import sobol as sobol_sample

from hmcore.model.deck_values import base_values
from hmcore.model.parameters import ParameterSpace
from hmcore.scoring.observations import ObservationSet

MORRIS_LEVELS = 4
"""Levels of the Morris grid (SALib's default; the step is levels / (2 (levels - 1)) = 2/3 of
the box)."""
MORRIS_MIN_TRAJECTORIES = 2
"""Fewest Morris trajectories: with one, sigma (the spread of the effects) is undefined."""
SOBOL_MIN_N = 16
"""Smallest Sobol' base sample N: below it the bootstrap confidence of S1 and ST is wider than
the indices themselves on a few parameters."""
SWITCH_ON_SHARE = 0.10
"""The rule: a parameter matters when its importance on the objective is at least this share of
the largest parameter's (see the module's docstring)."""
OVERALL = ("objective", "E")
"""The overall responses: the case's objective (what a match minimises) and E."""


class ScreenMethod(StrEnum):
    """How the parameter box is sampled and the effects estimated."""

    OAT = "oat"
    MORRIS = "morris"
    SOBOL = "sobol"


class Centre(StrEnum):
    """Where OAT starts: the prior centre (the middle of the box in the case's scaling) or the
    deck's own values (:func:`hmcore.model.deck_values.base_values`)."""

    PRIOR = "prior"
    DECK = "deck"


IMPORTANCE = {ScreenMethod.OAT: "swing", ScreenMethod.MORRIS: "mu_star",
              ScreenMethod.SOBOL: "ST"}
"""The column that ranks the parameters, per method."""


def minimum_budget(method: ScreenMethod, dim: int) -> int:
    """The fewest calls ``method`` needs on ``dim`` parameters."""
    if method is ScreenMethod.OAT:
        return 2 * dim + 1
    if method is ScreenMethod.MORRIS:
        return MORRIS_MIN_TRAJECTORIES * (dim + 1)
    return SOBOL_MIN_N * (dim + 2)


def default_budget(method: ScreenMethod, dim: int) -> int:
    """The budget when none is given: OAT's 2d + 1; 10 Morris trajectories; Sobol' with N=64."""
    if method is ScreenMethod.OAT:
        return 2 * dim + 1
    if method is ScreenMethod.MORRIS:
        return 10 * (dim + 1)
    return 64 * (dim + 2)


def budget_problem(method: ScreenMethod, dim: int, budget: int) -> str | None:
    """Why ``budget`` is too small for ``method`` on ``dim`` parameters (None when it is not)."""
    need = minimum_budget(method, dim)
    if budget >= need:
        return None
    why = {ScreenMethod.OAT: f"2d+1 = {need} (the centre and each of the {dim} parameters at "
                             "its two bounds)",
           ScreenMethod.MORRIS: f"{MORRIS_MIN_TRAJECTORIES}(d+1) = {need} "
                                f"({MORRIS_MIN_TRAJECTORIES} trajectories of {dim + 1} points)",
           ScreenMethod.SOBOL: f"N(d+2) = {SOBOL_MIN_N}x{dim + 2} = {need} (N >= {SOBOL_MIN_N})"}
    return f"budget {budget} is too small for {method.value} on {dim} parameters: it needs at " \
           f"least {why[method]}"


@dataclass(frozen=True)
class Design:
    """The points of a screening, in the unit box (``unit``, one row per call) and as the
    space's actions in [-1, 1] (``actions``); what SALib was told (``problem``, ``levels``,
    ``trajectories`` of Morris, ``base_n`` of Sobol'), and the seed."""

    method: ScreenMethod
    unit: np.ndarray
    problem: dict
    seed: int
    levels: int | None = None
    trajectories: int | None = None
    base_n: int | None = None
    centre: str = Centre.PRIOR.value

    @property
    def actions(self) -> np.ndarray:
        return 2.0 * self.unit - 1.0

    @property
    def calls(self) -> int:
        return len(self.unit)

    def describe(self) -> dict:
        return {"method": self.method.value, "calls": self.calls, "seed": self.seed,
                "levels": self.levels, "trajectories": self.trajectories, "base_n": self.base_n,
                **({"centre": self.centre} if self.method is ScreenMethod.OAT else {})}


def oat_centre(case, centre: str) -> dict[str, float] | None:
    """OAT's starting values in ``case``: None for the prior centre, the deck's own values
    (:func:`~hmcore.model.deck_values.base_values`) for ``deck``."""
    if centre != Centre.DECK.value:
        return None
    return base_values(case.info, case.space)


def salib_problem(space: ParameterSpace) -> dict:
    """SALib's problem of the unit box, one dimension per parameter of ``space``."""
    return {"num_vars": space.dim, "names": list(space.names), "bounds": [[0.0, 1.0]] * space.dim}


def design(method: ScreenMethod, space: ParameterSpace, budget: int, seed: int,
           centre: dict[str, float] | None = None) -> Design:
    """The screening's points within ``budget`` (ValueError when it is too small). ``centre``:
    OAT's starting values (the deck's own, clipped into the box); default the prior centre."""
    problem_text = budget_problem(method, space.dim, budget)
    if problem_text:
        raise ValueError(problem_text)
    problem = salib_problem(space)
    d = space.dim
    if method is ScreenMethod.OAT:
        start = np.full(d, 0.5) if centre is None else \
            np.clip((space.to_action(centre) + 1.0) / 2.0, 0.0, 1.0)
        unit = np.tile(start, (2 * d + 1, 1))
        for i in range(d):
            unit[1 + 2 * i, i] = 0.0
            unit[2 + 2 * i, i] = 1.0
        return Design(method, unit, problem, seed,
                      centre=(Centre.PRIOR if centre is None else Centre.DECK).value)
    if method is ScreenMethod.MORRIS:
        r = budget // (d + 1)
        unit = morris_sample.sample(problem, r, num_levels=MORRIS_LEVELS,
                                    seed=np.random.default_rng(seed))
        return Design(method, unit, problem, seed, levels=MORRIS_LEVELS, trajectories=r)
    n = 1 << int(np.floor(np.log2(budget / (d + 2))))
    unit = sobol_sample.sample(problem, n, calc_second_order=False, seed=seed)
    return Design(method, unit, problem, seed, base_n=n)


# ============================================================================ responses
def responses_of(records: list[dict], observations: ObservationSet, objective) -> pd.DataFrame:
    """One row per call (in call order), one column per response: ``objective`` (the case's
    objective's value), ``E``, and per well and quantity ``misfit:WELL:Q`` (mean squared
    whitened residual over the fitted history) and ``end:WELL:Q`` (the simulated value at the
    history end); NaN where a call failed."""
    rows = observations.rows
    idx = observations.vector_index("fit")
    series = rows.series.to_numpy()[idx]
    labels = {s: f"{w}:{q}" for s, w, q in zip(rows.series, rows.well, rows.quantity)}
    fit = rows[rows.period.to_numpy() == "fit"]
    last = fit.sort_values("days").groupby(["well", "quantity"], sort=True).tail(1)
    sigma = rows.sigma.to_numpy(float)
    observed = rows.observed.to_numpy(float)
    out = []
    for record in records:
        sim = record.get("simulated")
        row = {"objective": _finite(objective.value(record)) if sim is not None else np.nan,
               "E": _finite(record.get("E"))}
        sim = np.full(len(rows), np.nan) if sim is None else \
            np.array([np.nan if v is None else v for v in sim], float)
        failed = record.get("status") not in ("COMPLETE", "INVALID") or not np.isfinite(sim).any()
        e = observations.whiten((sim - observed) / sigma, "fit")
        for s in sorted(set(series)):
            row[f"misfit:{labels[s]}"] = np.nan if failed else float(np.mean(e[series == s] ** 2))
        for i, w, q in zip(last.index, last.well, last.quantity):
            row[f"end:{w}:{q}"] = np.nan if failed else float(sim[rows.index.get_loc(i)])
        out.append(row)
    return pd.DataFrame(out)


def _finite(v) -> float:
    return float(v) if v is not None and np.isfinite(float(v)) else np.nan


# ============================================================================ analysis
def analyse(d: Design, responses: pd.DataFrame) -> pd.DataFrame:
    """The ranked table: per response and parameter the method's measures, ``importance``
    (:data:`IMPORTANCE`), its ``rank`` within the response (1 = strongest) and ``share`` of the
    response's strongest; a response with a failed call (NaN) or no variation is left out."""
    names = d.problem["names"]
    frames = []
    for response in responses.columns:
        y = responses[response].to_numpy(float)
        if not np.isfinite(y).all() or np.ptp(y) == 0.0:
            continue
        frame = pd.DataFrame({"parameter": names, **_measures(d, y)})
        frame.insert(0, "response", response)
        frames.append(ranked(frame, IMPORTANCE[d.method]))
    if not frames:
        return pd.DataFrame(columns=["response", "parameter", "importance", "rank", "share"])
    return pd.concat(frames, ignore_index=True)


def _measures(d: Design, y: np.ndarray) -> dict[str, np.ndarray]:
    if d.method is ScreenMethod.OAT:
        centre, low, high = y[0], y[1::2], y[2::2]
        return {"low": low - centre, "high": high - centre, "swing": np.abs(high - low),
                "centre": np.full(len(low), centre)}
    if d.method is ScreenMethod.MORRIS:
        s = morris_analyze.analyze(d.problem, d.unit, y, num_levels=d.levels,
                                   seed=np.random.default_rng(d.seed))
        return {"mu_star": np.asarray(s["mu_star"], float), "sigma": np.asarray(s["sigma"], float),
                "mu": np.asarray(s["mu"], float),
                "mu_star_conf": np.asarray(s["mu_star_conf"], float)}
    s = sobol_analyze.analyze(d.problem, y, calc_second_order=False, seed=d.seed)
    return {"S1": np.asarray(s["S1"], float), "S1_conf": np.asarray(s["S1_conf"], float),
            "ST": np.asarray(s["ST"], float), "ST_conf": np.asarray(s["ST_conf"], float)}


def ranked(frame: pd.DataFrame, column: str) -> pd.DataFrame:
    """``frame`` (one response, one row per parameter) with ``importance`` (= ``column``,
    negative estimates, which Sobol' can give, as 0), ``rank`` (1 = strongest, ties by name) and
    ``share`` of the strongest, sorted by rank."""
    out = frame.copy()
    out["importance"] = np.clip(out[column].to_numpy(float), 0.0, None)
    out = out.sort_values(["importance", "parameter"], ascending=[False, True],
                          kind="stable").reset_index(drop=True)
    out["rank"] = np.arange(1, len(out) + 1)
    top = float(out["importance"].max())
    out["share"] = out["importance"] / top if top > 0 else 0.0
    return out


@dataclass(frozen=True)
class Choice:
    """The parameters that matter (``chosen``, strongest first), the response that chose them,
    and the rule in words."""

    chosen: tuple[str, ...]
    dropped: tuple[str, ...]
    response: str
    rule: str


def choose(table: pd.DataFrame, method: ScreenMethod, names: list[str],
           share: float = SWITCH_ON_SHARE) -> Choice:
    """Apply the rule on the objective (on E when the objective was not ranked): every
    parameter whose importance is at least ``share`` of the largest."""
    measure = {ScreenMethod.OAT: "swing", ScreenMethod.MORRIS: "mu*",
               ScreenMethod.SOBOL: "ST"}[method]
    for response in OVERALL:
        rows = table[table.response == response]
        if len(rows):
            chosen = tuple(rows.parameter[rows.share >= share])
            rule = (f"{measure} on the {response} is at least {share:.0%} of the largest "
                    f"parameter's ({rows.parameter.iloc[0]}, {measure} "
                    f"{rows.importance.iloc[0]:.4g})")
            return Choice(chosen, tuple(n for n in names if n not in chosen), response, rule)
    return Choice((), tuple(names), "", "no overall response could be ranked (failed calls)")


def screen_problems(source: str, dim: int, method: str, budget: int | None,
                    centre: str = Centre.PRIOR.value) -> list[str]:
    """Every reason to refuse a screening before any simulation, one line each with the file
    and key (or the option) at fault: an unknown method, a case without scalar parameters, a
    budget too small for the method."""
    problems = []
    known = [m.value for m in ScreenMethod]
    if method not in known:
        problems.append(f"--method {method}: unknown screening method; use one of "
                        f"{', '.join(known)}")
    if centre not in [c.value for c in Centre]:
        problems.append(f"--centre {centre}: use prior (the middle of each parameter's box) or "
                        "deck (the deck's own values)")
    elif centre != Centre.PRIOR.value and method != ScreenMethod.OAT.value:
        problems.append(f"--centre {centre}: only OAT starts from a centre; Morris and Sobol' "
                        "sample the whole box")
    if dim == 0:
        problems.append(f"{source} key 'parameters': no scalar parameter to screen; add "
                        "[[parameters]] tables (kind = \"multiply\", \"skin\", ...)")
    if budget is not None and budget < 1:
        problems.append(f"--budget {budget}: must be at least 1")
    elif method in known and dim > 0 and budget is not None:
        text = budget_problem(ScreenMethod(method), dim, budget)
        if text:
            problems.append(f"--budget {budget}: {text}")
    return problems


def default_screen_name(case_name: str, method: str, seed: int) -> str:
    """A screening's default name: CASE-screen-METHOD-seedS."""
    return f"{case_name}-screen-{method}-seed{seed}"
