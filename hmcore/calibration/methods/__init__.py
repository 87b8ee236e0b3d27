"""Calibration methods. Proposers (ask/tell) and drivers (their own loop, handed the evaluator)
never run the simulator; the caller evaluates what they ask and journals every call.

| name | method | library |
|---|---|---|
| ``sac`` | hmflow's SAC | stable-baselines3 |
| ``sac-paper`` | the reference paper's SAC, SB3's ``learn()`` | stable-baselines3 |
| ``random`` | uniform random search | numpy |
| ``sobol`` | scrambled Sobol' points | scipy.stats.qmc |
| ``cmaes`` | CMA-ES | cma |
| ``de`` | differential evolution | nevergrad |
| ``bo`` | Gaussian-process Bayesian optimisation | optuna (GPSampler) |
| ``lm`` | bounded least squares on the whitened residuals, multi-start (the default) | scipy.optimize |
| ``esmda`` | ensemble smoother with multiple data assimilation | iterative_ensemble_smoother |

The names, the default, versions and ablations: :mod:`hmcore.calibration.registry`.
Ablations of ``sac`` (:data:`~hmcore.calibration.registry.ABLATIONS`) are methods too: ``sac`` with one setting
changed, benchmarked at the same budget and judged by the same E. "Uniform proposals" is
``random`` (``sac`` without its policy).
"""

from hmcore.calibration.methods.base import Driver, Feedback, Proposal, Proposer
from hmcore.calibration.methods.random_search import RandomProposer
from hmcore.calibration.methods.sac import SACProposer, SACSettings
from hmcore.calibration.registry import (ABLATIONS, AGENTS, DEFAULT_AGENT, METHODS, VERSIONS,
                                         default_campaign_name, method_version)

def make_proposer(name: str, dim: int, seed: int, workers: int = 1, budget: int = 200,
                  **settings) -> Proposer | Driver:
    """Build a method by name (see the table above); ``settings`` go to the SAC variants."""
    if name in ABLATIONS:
        base, changed = ABLATIONS[name]
        return make_proposer(base, dim, seed, workers, budget, **{**changed, **settings})
    if settings and name not in ("sac", "sac-paper"):
        raise ValueError(f"agent {name!r} takes no settings, got {sorted(settings)}")
    if name == "sac":
        return SACProposer(dim, seed, SACSettings(**settings))
    # the methods below import their libraries (SB3, scipy.qmc, cma, nevergrad, optuna,
    # iterative_ensemble_smoother) only when built: importing them all costs seconds at start-up
    if name == "sac-paper":
        from hmcore.calibration.methods.sac_paper import PaperSAC, PaperSACSettings

        return PaperSAC(dim, seed, PaperSACSettings(**settings))
    if name == "random":
        return RandomProposer(dim, seed)
    if name == "sobol":
        from hmcore.calibration.methods.sobol import SobolProposer

        return SobolProposer(dim, seed)
    if name == "cmaes":
        from hmcore.calibration.methods.cmaes import CMAProposer

        return CMAProposer(dim, seed, workers)
    if name == "de":
        from hmcore.calibration.methods.de import DEProposer

        return DEProposer(dim, seed, budget, workers)
    if name == "bo":
        from hmcore.calibration.methods.bo import BOProposer

        return BOProposer(dim, seed)
    if name == "lm":
        from hmcore.calibration.methods.lm import LMDriver

        return LMDriver(dim, seed)
    if name == "esmda":
        from hmcore.calibration.methods.esmda import ESMDADriver

        return ESMDADriver(dim, seed)
    raise ValueError(f"agent must be one of {list(METHODS)}, got {name!r}")


def budget_problem(name: str, budget: int, workers: int) -> str | None:
    """Why ``budget`` / ``workers`` cannot run method ``name`` (None when they can)."""
    if name == "sac-paper" and budget % workers:
        return (f"sac-paper steps its {workers} env copies together: the budget {budget} must "
                f"be a multiple of the workers {workers} (e.g. "
                f"{max(workers, budget // workers * workers)})")
    if name == "esmda":
        from hmcore.calibration.methods.esmda import plan

        try:
            plan(budget)
        except ValueError as exc:
            return str(exc)
    return None


__all__ = ["ABLATIONS", "AGENTS", "DEFAULT_AGENT", "METHODS", "VERSIONS", "default_campaign_name", "method_version", "Driver", "Feedback", "Proposal", "Proposer", "RandomProposer",
           "SACProposer", "SACSettings", "budget_problem", "make_proposer"]
