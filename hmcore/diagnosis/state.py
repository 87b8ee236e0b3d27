"""The state of one round of a diagnosis: what every step works with, and each step's result.

Every result is frozen: a step is a function of the earlier steps' results that returns its
own (:func:`hmcore.diagnosis.calibration.calibrate` -> :class:`Calibrated`,
:func:`hmcore.diagnosis.residuals.analyse_residuals` -> the residual analysis,
:func:`hmcore.diagnosis.ranking.rank` -> :class:`Ranking`,
:func:`hmcore.diagnosis.recalibration.extend` -> :class:`Extension`,
:func:`hmcore.diagnosis.recalibration.recalibrate` -> :class:`Recalibration`, then the
decision's document); :class:`Round` holds those made so far. Each result's ``document`` is
what the flow stores as that step's JSON artifact. Scaled coordinates (``u``) are those of
:class:`hmcore.diagnosis.recalibrate.Coordinates`: [-1, 1] over each parameter's range.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from hmcore.diagnosis.candidate import Candidate
from hmcore.diagnosis.attribution import Score
from hmcore.diagnosis.recalibrate import Coordinates
from hmcore.diagnosis.runs import Run, Simulations
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.model.case import Case
from hmcore.scoring.observations import ObservationSet


@dataclass(frozen=True)
class Context:
    """What every step of a round works with."""

    case: Case
    """The case diagnosed (its ``history_end_days`` set: the residuals' split)."""
    settings: DiagnosisSettings
    """The knobs, the noise lines derived for ``n_tests`` candidates."""
    obs: ObservationSet
    """The noise model before the calibration (sigma from the data or the observed series)."""
    coords: Coordinates
    """Scaled coordinates of the case's own (global) parameters."""
    sims: Simulations
    """The round's simulator calls and their count against the budget."""
    n_tests: int
    """Candidates the noise lines count (:func:`hmcore.diagnosis.budget.count_tests`)."""
    log: Callable[[str], None]
    started: float
    """``time.perf_counter()`` when the round began (the document's wall time)."""


@dataclass(frozen=True)
class Calibrated:
    """Step 1: the calibrated model."""

    run: Run
    """Its simulation, residuals whitened under ``obs``."""
    u: np.ndarray
    """Its global parameters in scaled coordinates."""
    obs: ObservationSet
    """The noise model refined from its residuals: every later step's."""
    jacobian: np.ndarray | None
    """The calibration's last finite-difference Jacobian of the whitened fitted residuals in
    the globals, when taken close enough to ``u`` to serve the ranking (None: the ranking
    takes its own)."""
    document: dict
    """``calibration.json``."""


@dataclass(frozen=True)
class Ranking:
    """Step 3: every candidate's score test at the calibrated point."""

    candidates: tuple[Candidate, ...]
    """The library's candidates, then the dated and the moved ones the ranking added."""
    union_case: Case
    """The case with every candidate's parameter (each run sets the ones it moves)."""
    scores: dict[str, Score]
    sensitivity: dict[str, np.ndarray]
    """Per candidate id: d(whitened fitted residuals) / d(its scaled coordinate)."""
    probe_runs: dict[str, Run]
    jacobian: np.ndarray
    """The globals' Jacobian the score tests projected out (reused or taken here)."""
    held: np.ndarray
    """Globals pressed against a bound (not projected out)."""
    document: dict
    """``ranking.json``."""


@dataclass(frozen=True)
class Extension:
    """Step 4: the leading candidates to recalibrate, best first."""

    ids: tuple[str, ...]
    document: dict
    """``extension.json``: each extended model's parameters and start."""


@dataclass(frozen=True)
class Recalibration:
    """Step 5: each leading candidate recalibrated and judged."""

    confirmed: dict[str, dict]
    """Per candidate id, its record (:func:`hmcore.diagnosis.confirmation.record`)."""
    runs: dict[str, Run]
    """Per candidate id, the run of its recalibrated model."""
    document: dict
    """``recalibration.json``."""


@dataclass(frozen=True)
class Round:
    """The results of a round's steps so far (None: not run yet) and their wall times."""

    calibrated: Calibrated | None = None
    residuals: dict | None = None
    """Step 2: :func:`hmcore.diagnosis.residuals.analyse_residuals` of the calibrated model
    (``residuals.json``)."""
    ranking: Ranking | None = None
    extension: Extension | None = None
    recalibration: Recalibration | None = None
    document: dict | None = None
    """Step 6: the decision (``diagnosis.json`` of the round)."""
    timings: dict[str, float] = field(default_factory=dict)
    """Wall seconds per step."""
