"""Diagnosis of a calibrated case: residuals beyond noise, candidate model extensions, their
attribution by a score test, warm-started recalibration and the measured gain.

Free of Prefect: the simulator is reached only through an injected ``evaluate_batch``.
"""

from hmcore.diagnosis.attribution import Score, projector_basis, score_test
from hmcore.diagnosis.diagnose import (Diagnosis, DiagnosisSettings, diagnose,
                                       local_evaluator)
from hmcore.diagnosis.extensions import KINDS, Candidate, build_candidates, extended_space
from hmcore.diagnosis.recalibrate import Coordinates, LevenbergMarquardt, LMSettings, run_lockstep
from hmcore.diagnosis.residuals import ObservationSet, analyse_residuals, estimate_noise

__all__ = ["KINDS", "Candidate", "Coordinates", "Diagnosis", "DiagnosisSettings",
           "LMSettings", "LevenbergMarquardt", "ObservationSet", "Score", "analyse_residuals",
           "build_candidates", "diagnose", "estimate_noise", "extended_space", "local_evaluator",
           "projector_basis", "run_lockstep", "score_test"]
