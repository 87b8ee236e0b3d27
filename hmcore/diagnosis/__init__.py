"""Diagnosis of a calibrated case: residuals beyond noise, candidate model extensions, their
attribution by a score test, warm-started recalibration and the measured gain.

One job per module. The knobs: :mod:`~hmcore.diagnosis.settings` (``DiagnosisSettings``,
``--kinds``), :mod:`~hmcore.diagnosis.budget` (the minimum of simulator calls). The pieces:
:mod:`~hmcore.diagnosis.residuals` (residual analysis), :mod:`~hmcore.diagnosis.candidate`
(a candidate as data, the families' names and ranges), :mod:`~hmcore.diagnosis.extensions`
(the families that build candidates), :mod:`~hmcore.diagnosis.attribution` (the score test),
:mod:`~hmcore.diagnosis.screening` (the ranking's runs and scores),
:mod:`~hmcore.diagnosis.dating` (start dates), :mod:`~hmcore.diagnosis.recalibrate` (bounded
Levenberg-Marquardt), :mod:`~hmcore.diagnosis.refit` (start points and restarts: numerics),
:mod:`~hmcore.diagnosis.confirmation` (the fit line and the held-back rule),
:mod:`~hmcore.diagnosis.decision` (the ranked causes, the verdict). One round, state and steps:
:mod:`~hmcore.diagnosis.runs` (the budgeted simulations), :mod:`~hmcore.diagnosis.state` (each
step's frozen result), :mod:`~hmcore.diagnosis.calibration`, :mod:`~hmcore.diagnosis.ranking`,
:mod:`~hmcore.diagnosis.recalibration`, :mod:`~hmcore.diagnosis.restart` (the steps),
:mod:`~hmcore.diagnosis.workflow` (``Diagnosis``: the steps in order). All rounds:
:mod:`~hmcore.diagnosis.forward` (a second cause, with the first in the model),
:mod:`~hmcore.diagnosis.origins` (a later fitted window), :mod:`~hmcore.diagnosis.rounds` (all
of them, in order), :mod:`~hmcore.diagnosis.report` (``report.md``, plots, the files).
Hidden-effect test cases are :mod:`hmcore.scenarios`'.

Free of Prefect: the simulator is reached only through an injected ``evaluate_batch``.
"""

from hmcore.diagnosis.attribution import Score, projector_basis, score_test
from hmcore.diagnosis.candidate import KINDS, Candidate, extended_space
from hmcore.diagnosis.extensions import build_candidates
from hmcore.diagnosis.recalibrate import Coordinates, LevenbergMarquardt, LMSettings, run_lockstep
from hmcore.scoring.observations import ObservationSet
from hmcore.diagnosis.residuals import analyse_residuals
from hmcore.scoring.noise import estimate_noise
from hmcore.diagnosis.settings import DiagnosisSettings, parse_kinds
from hmcore.diagnosis.budget import budget_problem, minimum_runs
from hmcore.diagnosis.runs import local_evaluator
from hmcore.diagnosis.workflow import Diagnosis
from hmcore.diagnosis.rounds import diagnose, diagnose_all

__all__ = ["KINDS", "Candidate", "Coordinates", "Diagnosis", "DiagnosisSettings",
           "LMSettings", "LevenbergMarquardt", "ObservationSet", "Score", "analyse_residuals",
           "budget_problem", "build_candidates", "diagnose", "diagnose_all", "estimate_noise",
           "extended_space", "local_evaluator", "minimum_runs", "parse_kinds", "projector_basis",
           "run_lockstep", "score_test"]
