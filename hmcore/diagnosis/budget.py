"""The simulator calls a diagnosis cannot do without, and the check of a budget against them.

Counts only, from the case and the settings; nothing here simulates. The ranking's calls are
set aside before the calibration spends any (:func:`ranking_reserve`); a budget below
:func:`minimum_runs` is refused before the first call (:func:`budget_problem`).
"""

from __future__ import annotations

from hmcore.diagnosis.extensions import SHIFTS, build_candidates
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.errors import Problem
from hmcore.model.case import Case


def minimum_runs(case: Case, settings: DiagnosisSettings, given: bool) -> int:
    """Simulator calls a diagnosis of ``case`` cannot do without: the calibrated model (one
    run of a ``given`` vector; otherwise the deck's values and their finite differences, one
    run per global parameter), then the ranking (one probe per candidate of
    ``settings.kinds`` and one finite difference per global parameter)."""
    dim = len(case.space.parameters)
    n_candidates = len(build_candidates(case.info, case.space, None, settings.kinds))
    return (1 if given else dim + 1) + n_candidates + dated_reserve(case, settings) + dim


def dated_reserve(case: Case, settings: DiagnosisSettings) -> int:
    """Probe runs of the dated candidates the ranking may add (``productivity_change``)."""
    if "productivity_change" not in settings.kinds:
        return 0
    return min(settings.dated_max, len(case.info.producers))


def shift_tests(case: Case, settings: DiagnosisSettings) -> int:
    """Moved regional boxes the ranking may probe: candidates in the noise lines' count (run
    only when the budget leaves room, so not in :func:`minimum_runs`)."""
    if "regional_permeability" not in settings.kinds:
        return 0
    return len(SHIFTS) * min(settings.region_shifts, len(case.info.producers))


def count_tests(case: Case, settings: DiagnosisSettings) -> int:
    """The candidates a diagnosis of ``case`` may test (the Bonferroni count of its noise
    lines): the library's of ``settings.kinds``, the dated ones and the moved boxes."""
    return (len(build_candidates(case.info, case.space, None, settings.kinds))
            + dated_reserve(case, settings) + shift_tests(case, settings))


def ranking_reserve(case: Case, settings: DiagnosisSettings) -> int:
    """Calls the ranking needs at most: a probe per candidate, a difference per global."""
    return (len(build_candidates(case.info, case.space, None, settings.kinds))
            + dated_reserve(case, settings) + len(case.space.parameters))


def budget_problem(case: Case, settings: DiagnosisSettings, given: bool,
                   where: str = "--budget") -> Problem | None:
    """A :class:`Problem` when ``settings.budget`` cannot cover :func:`minimum_runs`."""
    if settings.budget is None:
        return None
    need = minimum_runs(case, settings, given)
    if settings.budget >= need:
        return None
    dim = len(case.space.parameters)
    dated = dated_reserve(case, settings)
    n = need - (1 if given else dim + 1) - dim - dated
    start = "1 run of the given parameters" if given else \
        f"{dim + 1} to calibrate from the deck's values"
    dated_text = f", {dated} for dated candidates" if dated else ""
    return Problem(where, f"{settings.budget} simulator calls cannot cover the minimum of "
                          f"{need} ({start}, then {n} candidate probes{dated_text} and {dim} "
                          "finite differences for the ranking)",
                   f"give {where} {need} or more, about {need + 40} to leave room for the "
                   "recalibrations, or search fewer kinds with "
                   f"{'--kinds' if where.startswith('--') else 'kinds'}")
