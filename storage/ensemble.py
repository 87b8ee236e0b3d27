"""Where an ensemble run (``hmflow ensemble``, issue 41) keeps its things in the store.

``ROOT/<campaign>/`` of an ensemble run::

    campaign.json                     the settings the name is bound to
    case/v0001/                       the case as run (as a calibration campaign's)
    ensemble-00/v0001/                the prior: ensemble.parquet (one row per parameter, one
                                      float32 column per member), ensemble.json (seeds, layout,
                                      the grid's dims), grid.parquet (the active cells' global
                                      indices: where a parameter's cell sits on a map)
    ensemble-01/v0001/ ...            the ensemble after assimilation 1, 2, ... (the last one
                                      is the posterior)
    evaluations-members-00/           the journal of the prior's member runs (one record per
                                      member, written when its run ends); -01 ... the next
                                      ensembles', the last one the posterior run
    ensemble-runs/i00-m0003/ ...      the members' run directories
    forecast/v0001/                   forecast.parquet (P90/P50/P10, prior and posterior),
                                      members.parquet, summary.json (iterations, failures),
                                      curves.parquet (every prior and posterior member's curves,
                                      whole schedule), misfit.parquet (every member's data
                                      misfit, every round of runs)
    report/v0001/                     report.md, report.html, report.json and the PNG figures
                                      (tasks.ensemble_report; rebuilt by hmflow report)
"""

from __future__ import annotations

from .store import validate_name

ENSEMBLE_RUNS = "ensemble-runs"
"""Folder of the members' run directories."""
FORECAST_STEP = "forecast"
ENSEMBLE_FILE = "ensemble.parquet"
ENSEMBLE_DOC = "ensemble.json"
GRID_FILE = "grid.parquet"
CURVES_FILE = "curves.parquet"
MISFIT_FILE = "misfit.parquet"
REPORT_STEP = "report"


def ensemble_step(iteration: int) -> str:
    """The step of the ensemble before assimilation ``iteration`` (0: the prior; after the
    last assimilation: the posterior)."""
    return validate_name("step", f"ensemble-{_check(iteration):02d}")


def member_journal(iteration: int) -> str:
    """The journal name (:class:`storage.EvaluationJournal`'s ``name``) of the runs of the
    ensemble ``ensemble_step(iteration)``; a record's index is the member's."""
    return validate_name("journal", f"members-{_check(iteration):02d}")


def member_run_name(iteration: int) -> str:
    """The run directory name of a member of ensemble ``iteration``, as a format with
    ``{index}`` (the member): ``i01-m{index:04d}``."""
    return f"i{_check(iteration):02d}-m{{index:04d}}"


def _check(iteration: object) -> int:
    if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
        raise ValueError(f"an ensemble iteration must be an integer >= 0, got {iteration!r}")
    return iteration
