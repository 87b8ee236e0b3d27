"""Diagnosis of a calibrated case: residuals beyond noise, candidate model extensions, their
attribution by a score test, warm-started recalibration and the measured gain.

One job per module: :mod:`~hmcore.diagnosis.settings` (the knobs, ``--kinds``),
:mod:`~hmcore.diagnosis.residuals` (noise and whitened residuals),
:mod:`~hmcore.diagnosis.extensions` (the candidate library),
:mod:`~hmcore.diagnosis.attribution` (the score test), :mod:`~hmcore.diagnosis.screening`
(ranking the candidates), :mod:`~hmcore.diagnosis.recalibrate` (bounded Levenberg-Marquardt),
:mod:`~hmcore.diagnosis.refit` (start points and restarts of the extended models),
:mod:`~hmcore.diagnosis.decision` (accept or veto, the ranked causes),
:mod:`~hmcore.diagnosis.workflow` (one round's steps, the budget), :mod:`~hmcore.diagnosis.forward`
(a second cause, with the first in the model), :mod:`~hmcore.diagnosis.origins` (a later fitted
window), :mod:`~hmcore.diagnosis.rounds` (all of them, in order), :mod:`~hmcore.diagnosis.report`
and :mod:`~hmcore.scenarios.hidden` (hidden-effect test cases).

Free of Prefect: the simulator is reached only through an injected ``evaluate_batch``.
"""

from hmcore.diagnosis.attribution import Score, projector_basis, score_test
from hmcore.diagnosis.extensions import KINDS, Candidate, build_candidates, extended_space
from hmcore.diagnosis.recalibrate import Coordinates, LevenbergMarquardt, LMSettings, run_lockstep
from hmcore.scoring.observations import ObservationSet
from hmcore.diagnosis.residuals import analyse_residuals
from hmcore.scoring.noise import estimate_noise
from hmcore.diagnosis.settings import DiagnosisSettings, parse_kinds
from hmcore.diagnosis.workflow import Diagnosis, budget_problem, local_evaluator, minimum_runs
from hmcore.diagnosis.rounds import diagnose, diagnose_all

__all__ = ["KINDS", "Candidate", "Coordinates", "Diagnosis", "DiagnosisSettings",
           "LMSettings", "LevenbergMarquardt", "ObservationSet", "Score", "analyse_residuals",
           "budget_problem", "build_candidates", "diagnose", "diagnose_all", "estimate_noise", "extended_space",
           "local_evaluator", "minimum_runs", "parse_kinds", "projector_basis", "run_lockstep",
           "score_test"]
