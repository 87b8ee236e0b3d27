"""The knobs of a diagnosis, and the checks of what a user asks for before any simulation.

:class:`DiagnosisSettings` holds every threshold and step size of the steps (screening,
recalibration, decision); :func:`parse_kinds` turns ``--kinds well_skin,aquifer_strength`` into
the families to search, refusing unknown names with a suggestion. Nothing here simulates.
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field
from typing import Iterable

from hmcore.diagnosis.candidate import DEFAULT_KINDS, KINDS
from hmcore.diagnosis.recalibrate import LMSettings
from hmcore.errors import Problem


@dataclass(frozen=True)
class DiagnosisSettings:
    """Knobs of a diagnosis.

    Units: *chi2* is the chi-square unit of the whitened residuals (residual / noise sigma,
    time correlation removed), in which one free parameter fitting pure noise removes 1 on
    average; *scaled* is the recalibration's coordinate, [-1, 1] over a parameter's range (log
    scale for factors, :class:`hmcore.diagnosis.recalibrate.Coordinates`). Which defaults were
    measured, on what, and what was tried instead: docs/diagnosis.md, "Where the settings'
    values come from"."""

    kinds: tuple[str, ...] = DEFAULT_KINDS
    """Families of candidate extensions searched (default :data:`DEFAULT_KINDS`; every one of
    :data:`hmcore.diagnosis.KINDS` can be asked for)."""
    confirm_top: int = 4
    """Candidates recalibrated at least (count), the best score tests first."""
    confirm_max: int = 6
    """Candidates recalibrated at most (count) when the leader's chi2 is at least
    ``weak_lead``."""
    confirm_close: float = 0.75
    """Beyond ``confirm_top``, a candidate is recalibrated too (up to ``confirm_max``) while
    its score test reaches this share (fraction) of the leader's chi2: when the globals
    absorbed a strong effect, several candidates score alike and the linear ranking cannot
    order them. Measured."""
    weak_lead: float = 50.0
    """When the leader's score test removes less than this (chi2), every screened candidate
    is recalibrated, up to ``confirm_weak_max``: near the line the linear ranking cannot be
    trusted (a response that bends, several candidates the globals absorb alike). Measured."""
    confirm_weak_max: int = 10
    """Candidates recalibrated at most (count) under a weak lead."""
    false_alarm: float = 0.003
    """Family-wise false-alarm rate (probability) of the noise lines ``chi2_threshold`` and
    ``fit_threshold`` when they are not given: the line over K candidates is the
    chi-square(1) quantile at ``false_alarm / K`` (Bonferroni, :func:`noise_line`), K the
    diagnosis's own count (:func:`hmcore.diagnosis.budget.count_tests`): 15.1 over 30
    candidates, 11.4 over 4. Measured."""
    chi2_threshold: float | None = None
    """A candidate is beyond noise when its score test removes more than this (chi2); None:
    derived (:func:`noise_line` of the diagnosis's candidates at ``false_alarm``)."""
    screen_threshold: float = 8.0
    """Candidates whose score test removes at least this much (chi2), even under
    ``chi2_threshold``, are recalibrated too: the score test is linear in the new parameter,
    and a strong effect seen through a curved response (a layer's permeability, a baffle) can
    land just under the line. Such a candidate ranks above ``none`` only when its
    recalibration lowers the fitted SSR by more than ``fit_threshold``. Measured."""
    fit_threshold: float | None = None
    """A recalibrated extension must lower the fitted SSR by more than this (chi2); None:
    derived, the same line as ``chi2_threshold`` (a likelihood-ratio test of one more
    parameter). A dated cause (its factor and its date) must pass the chi-square(2) line at
    the same tail probability (:func:`hmcore.diagnosis.confirmation.fit_line`)."""
    partial_share: float = 0.5
    """Share (fraction) of the misfit beyond noise (the calibrated model's SSR less its noise
    expectation) a selected cause must remove to be the whole answer: below it the verdict
    says the cause is partial (the selection is not changed). When the cause removes less
    than this share of the held-back and of the fitted misfit beyond noise, the model with it
    still misses the held-back history beyond noise, and round 2 finds residuals no family
    explains, ``unexplained`` leads and the cause is listed second
    (:func:`hmcore.diagnosis.decision.lead_unexplained`)."""
    derived_lines: tuple[str, ...] = ()
    """The lines derived from ``false_alarm`` rather than given (set on construction; a
    diagnosis derives them again for its own count of candidates, :func:`with_lines`)."""
    heldout_threshold: float = 6.0
    """The held-back rule (:func:`hmcore.diagnosis.confirmation.heldout_confirms`): an
    extension must lower the held-back whitened SSR by more than this (chi2), and the
    held-back E. When the calibrated model already fits the held-back history within noise
    (its SSR under the chi-square mean + ``quiet_sd`` standard deviations) it must lower the
    held-back E and not raise the held-back SSR by more than this. Measured."""
    quiet_sd: float = 3.0
    """Standard deviations of the held-back SSR's chi-square distribution: above its mean by
    more than this the held-back history is missed beyond noise, and a drop by more than this
    is decisive (:func:`hmcore.diagnosis.confirmation.heldout_noise_line`,
    :func:`hmcore.diagnosis.confirmation.heldout_decisive_drop`). Measured."""
    heldout_e_slack: float = 0.25
    """When the held-back whitened SSR drops decisively, the held-back E may rise by up to
    this share (fraction) and the held-back history still confirms: E weights every point
    alike whatever its noise, and noisy responses can raise it for the truth itself.
    Measured."""
    unexplained_alpha: float = 0.05
    """Family-wise false-alarm rate (probability) of a residual finding of the calibrated
    model (a well's response over a period, biased or drifting): when nothing is accepted, a
    finding beyond it makes the answer ``unexplained``, localised, instead of ``none``; its |z|
    must exceed ``norm.isf(alpha / (2 m))`` over the m bias and trend tests made
    (:func:`hmcore.diagnosis.decision.localise`)."""
    evidence_mass: float = 0.9
    """Weight (fraction) the answer's explanations must carry together
    (:mod:`hmcore.diagnosis.evidence`): one cause when its own weight reaches it (a Bayes
    factor of at least 9 over the next), else the smallest set, best first, that does - the
    explanations the data cannot separate."""
    max_causes: int = 2
    """Causes accepted at most (1 or 2), by greedy forward selection: when round 1 accepts a
    cause - or finds one that fits the fitted history beyond noise but that the held-back
    history vetoes - round 2 puts it in the model and diagnoses again
    (:mod:`hmcore.diagnosis.forward`). A vetoed first cause is accepted only with a second one
    that makes the pair predict the held-back history."""
    later_origins: tuple[float, ...] = (0.875,)
    """Ends of the later fitted windows (fractions of the record, first to last observed day,
    increasing): when a diagnosis accepts nothing and its calibrated model misses the
    held-back history beyond noise, it diagnoses again with the window ending at the first of
    these beyond the current end, and so on while no window names a cause (a rolling origin,
    :mod:`hmcore.diagnosis.origins`; empty: never)."""
    later_min_heldout: int = 20
    """Observed points a later window must leave to hold back (count)."""
    dated_max: int = 2
    """Dated candidates (``productivity_change``) the ranking adds at most (count of wells),
    one probe run each (:mod:`hmcore.diagnosis.dating`)."""
    region_shifts: int = 2
    """Wells (count, the strongest regional candidates beyond noise first) whose box the
    ranking also tries moved by its half width in i, j or both - the well at an edge or a
    corner of the box, 8 more probe runs a well - for a region beside a well rather than
    centred on it (:func:`hmcore.diagnosis.extensions.shifted_regions`; 0: never). They count
    as candidates in the noise lines whether or not they are run, and are run only when the
    budget leaves room for them."""
    dating_alpha: float = 0.05
    """Family-wise false-alarm rate (probability) of a start date: a date is kept when its
    chi2 gain over the undated change reaches what noise makes with this probability over the
    dates scanned (chi-square(1), Bonferroni: :func:`noise_line` over the dates)."""
    dating_min_after: int = 6
    """A date is scanned when the well has at least this many fitted points after it
    (count)."""
    tie_band: float = 10.0
    """Recalibrated candidates whose fitted SSR is within this (chi2) of the best fit, which
    the fitted history cannot tell apart: the held-back history orders them. Measured."""
    calibration: LMSettings = field(default_factory=lambda: LMSettings(
        fd_step=0.1, max_iter=10, max_evaluations=40, trials=2, ftol=0.02))
    """Phase 1 of the calibration (weighted least squares before the noise is refined)."""
    polish: LMSettings = field(default_factory=lambda: LMSettings(
        fd_step=0.1, max_iter=4, max_evaluations=16, trials=2, ftol=0.005))
    """Phase 2 of the calibration (prewhitened residuals)."""
    recalibration: LMSettings = field(default_factory=lambda: LMSettings(
        fd_step=0.1, max_iter=8, max_evaluations=12, trials=1, ftol=0.005))
    """Each leading candidate's recalibration (warm start, Broyden updates, lockstep)."""
    refine: LMSettings = field(default_factory=lambda: LMSettings(
        fd_step=0.1, max_iter=3, max_evaluations=12, trials=1, ftol=0.005))
    """The best recalibrated candidates continue from a fresh finite-difference Jacobian."""
    refine_top: int = 2
    """Recalibrated candidates refined at most (count): the best fits beyond noise."""
    restart: LMSettings = field(default_factory=lambda: LMSettings(
        fd_step=0.1, max_iter=6, max_evaluations=18, trials=1, ftol=0.005))
    """The restart from the deck's values (:mod:`hmcore.diagnosis.restart`): when the
    calibration pressed globals against their bounds, or the held-back history vetoes the best
    fits, they may have absorbed what an extension explains better, and a warm-started
    recalibration rarely leaves that basin."""
    near_bound: float = 0.05
    """Distance to a bound (scaled) that counts as "at the bound" for the restart (negative:
    no restarts on bounds)."""
    open_end: float = 0.01
    """The verdict warns that a selected cause stopped within this distance (scaled) of an end
    of its range that is not a physical limit of its family: it may stand in for something it
    does not describe (:func:`hmcore.diagnosis.candidate.open_end`; negative: never). A
    warning, not a veto: a veto was tried and gave worse models."""
    restart_top: int = 2
    """Recalibrated candidates restarted (count, best fits first), and with them every other
    one whose warm fit is within ``tie_band`` of the best and beyond noise (the fitted history
    cannot tell those apart, so each gets the same chance from the deck's values). A restart
    costs about 20 runs. Measured."""
    restart_max: int = 4
    """Restarts at most (count)."""
    restart_on_veto: bool = True
    """Also restart, when no global is at its bound, the recalibrated candidates that fit
    beyond noise but that the held-back history does not plainly confirm (see
    :func:`hmcore.diagnosis.refit.veto_restart_choice`)."""
    restart_grid: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)
    """Candidate values (scaled) tried with the globals at the deck's values before each
    restart; the best (or the candidate's recalibrated value) starts it."""
    restart_prior_sd: float = 0.5
    """Standard deviation (scaled; 0.5 = a quarter of the range) of the Gaussian prior on the
    globals at the deck's values that a restart adds to the fitted SSR: the extension on the
    model as given, the globals moved as little as the data need; without it a restart drifts
    back into the valley the globals made. Measured."""
    restart_slack: float = 5.0
    """A restart counts when its fitted SSR + prior is below the warm start's (prior of the
    warm start's globals) and its fitted SSR at most this much (chi2) above the warm start's:
    of fits the fitted history cannot tell apart, the one closer to the model as given."""
    line_search: tuple[float, ...] = (0.5, 1.0, 1.5)
    """Multiples of the score test's linear step tried along each leading candidate's joint
    direction (see :func:`hmcore.diagnosis.refit.joint_direction`) before its
    recalibration; the best point starts it."""
    global_fd_step: float = 0.1
    """Finite-difference step (scaled) of the globals' Jacobian the ranking takes."""
    reuse_jacobian_within: float = 0.15
    """Reuse the calibration's last finite-difference Jacobian of the globals for the ranking
    when the calibration moved less than this (scaled, in every global) since computing it."""
    heldout_fraction: float = 0.25
    """Share (fraction) of the record held back when the case sets no
    ``history_end_days``."""
    plots: bool = True
    """Write the residual plots (one PNG per named well) with the report."""
    polish_given: bool = True
    """Polish a given calibrated vector (e.g. a campaign's best) with phase 2 of the
    calibration, so that an extension's gain is not the globals' unfinished fit."""
    workers: int = 2
    """Simulations the evaluator runs at once (recalibration batches are filled to it)."""
    budget: int | None = None
    """Cap on simulator calls, every one counted (None: as many as the steps need). The
    ranking needs one run per candidate (+ one per global parameter) and is reserved first;
    the calibration and the recalibrations share the rest (see
    :func:`hmcore.diagnosis.budget.minimum_runs`)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "kinds", tuple(self.kinds))
        derived = tuple(self.derived_lines) + tuple(
            n for n in ("chi2_threshold", "fit_threshold") if getattr(self, n) is None)
        object.__setattr__(self, "derived_lines", tuple(dict.fromkeys(derived)))
        for name in self.derived_lines:  # until a diagnosis counts its own candidates
            if getattr(self, name) is None:
                object.__setattr__(self, name, noise_line(DEFAULT_TESTS, self.false_alarm))
        object.__setattr__(self, "later_origins", tuple(self.later_origins))
        problems = kinds_problems(self.kinds, "kinds")
        if self.budget is not None and self.budget < 1:
            problems.append(Problem("budget", f"must be at least 1, got {self.budget}",
                                    "give a positive number of simulator calls, or none"))
        if self.max_causes not in (1, 2):
            problems.append(Problem("max_causes", f"must be 1 or 2, got {self.max_causes}",
                                    "give 1 (one cause) or 2 (forward selection of a second)"))
        bad = [f for f in self.later_origins if not 0.0 < f < 1.0]
        if bad:
            problems.append(Problem("later_origins", f"fractions of the record must lie in "
                                    f"(0, 1), got {bad}", "give e.g. (0.875,), or () for none"))
        if list(self.later_origins) != sorted(set(self.later_origins)):
            problems.append(Problem("later_origins", "the ends of the later windows roll on in "
                                    "time order: they must increase, got "
                                    f"{list(self.later_origins)}",
                                    f"give {tuple(sorted(set(self.later_origins)))}"))
        if not 0.0 < self.false_alarm < 1.0:
            problems.append(Problem("false_alarm", f"must lie in (0, 1), got {self.false_alarm}",
                                    "give a probability such as 0.003"))
        if self.region_shifts < 0:
            problems.append(Problem("region_shifts", f"must be at least 0, got "
                                    f"{self.region_shifts}", "give 0 (never) or a number of "
                                    "wells, such as 2"))
        if not 0.5 <= self.evidence_mass < 1.0:
            problems.append(Problem("evidence_mass", f"must be in [0.5, 1), got "
                                    f"{self.evidence_mass}", "give a weight such as 0.9"))
        if self.workers < 1:
            problems.append(Problem("workers", f"must be at least 1, got {self.workers}",
                                    "give a positive number of simulations at once"))
        if problems:
            raise ValueError("; ".join(map(str, problems)))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


DEFAULT_TESTS = 30
"""About the candidates a full search of a small field has (count): the one the noise lines
assume until a diagnosis counts its own (see docs/diagnosis.md, "Where the settings' values
come from")."""


def noise_line(n_tests: int, false_alarm: float) -> float:
    """The chi2 a one-parameter extension removes from pure noise with probability at most
    ``false_alarm`` over ``n_tests`` candidates: the chi-square(1) quantile at
    ``false_alarm / n_tests`` (Bonferroni)."""
    from scipy.stats import chi2  # slow to import: only when needed

    return float(chi2.isf(false_alarm / max(int(n_tests), 1), 1))


def with_lines(s: DiagnosisSettings, n_tests: int) -> DiagnosisSettings:
    """``s`` with its derived lines (``s.derived_lines``) for ``n_tests`` candidates."""
    if not s.derived_lines:
        return s
    line = noise_line(n_tests, s.false_alarm)
    return dataclasses.replace(s, **{n: line for n in s.derived_lines})


def kinds_problems(kinds: Iterable[str], where: str = "--kinds") -> list[Problem]:
    """A :class:`Problem` per name in ``kinds`` that is not a family of extensions (with the
    closest family as the suggested fix), and one for an empty list."""
    kinds = list(kinds)
    if not kinds:
        return [Problem(where, "names no family of extensions",
                        f"give one or more of {', '.join(KINDS)} (comma-separated)")]
    out = []
    for name in kinds:
        if name in KINDS:
            continue
        close = difflib.get_close_matches(name, KINDS, n=1, cutoff=0.5)
        hint = f"did you mean {close[0]!r}? " if close else ""
        out.append(Problem(where, f"unknown kind of extension {name!r}",
                           f"{hint}the kinds are {', '.join(KINDS)}"))
    return out


def parse_kinds(text: str | Iterable[str], where: str = "--kinds") -> tuple[str, ...]:
    """The families named in ``text`` (comma- or space-separated, or a list of names), in the
    order of :data:`KINDS`. ValueError with every unknown name (and a suggestion) otherwise."""
    names = text.replace(",", " ").split() if isinstance(text, str) else \
        [n.strip() for n in text if n.strip()]
    names = list(dict.fromkeys(names))
    problems = kinds_problems(names, where)
    if problems:
        raise ValueError("; ".join(map(str, problems)))
    return tuple(k for k in KINDS if k in names)
