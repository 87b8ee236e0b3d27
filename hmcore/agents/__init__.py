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

Ablations of ``sac`` (:data:`ABLATIONS`, issue 14) are methods too: ``sac`` with one setting
changed, benchmarked at the same budget and judged by the same E. "Uniform proposals" is
``random`` (``sac`` without its policy).
"""

from hmcore.agents.base import Driver, Feedback, Proposal, Proposer
from hmcore.agents.random_search import RandomProposer
from hmcore.agents.lm import VERSION as LM_VERSION
from hmcore.agents.sac import VERSION as SAC_VERSION
from hmcore.agents.sac import SACProposer, SACSettings

AGENTS = ("sac", "sac-paper", "random", "sobol", "cmaes", "de", "bo", "lm", "esmda")
DEFAULT_AGENT = "lm"
"""The method a campaign runs unless told otherwise: the winner of the equal-budget benchmark
(docs/benchmarks.md, issue 14). It was ``sac`` until 2026-11-25: on PUNQ-S3's measured history
(5 seeds x 100 calls) ``lm`` reached 1.1x the floor in a median of 13 calls and ``sac`` never
reached 1.2x; the same order held on the synthetic case and on PUNQ-S3 histories made from
moved globals."""
VERSIONS = {"sac": SAC_VERSION, "lm": LM_VERSION}
"""A method whose proposals changed: campaigns are bound to the version that made their calls
(a resume under another version is refused; a benchmark names its campaigns after it)."""


ABLATIONS: dict[str, tuple[str, dict]] = {
    "sac-ent-fixed": ("sac", {"ent_coef": 0.01}),        # entropy fixed at auto's start value
    "sac-replay-1": ("sac", {"gradient_steps": 1}),      # 1 update per call, not 8: less reuse
    "sac-no-penalty": ("sac", {"penalty_in_reward": False}),  # learns E alone, without P
    "sac-robust": ("sac", {"robust_lambda": 0.5}),       # learns E + 0.5 x worst well-response
}
"""Each ablation: the method it varies and the settings it changes."""

METHODS = AGENTS + tuple(ABLATIONS)
"""Everything a campaign or a benchmark can run."""


def method_version(name: str) -> int:
    return VERSIONS.get(ABLATIONS[name][0] if name in ABLATIONS else name, 1)


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
    if name == "sac-paper":
        from hmcore.agents.sac_paper import PaperSAC, PaperSACSettings

        return PaperSAC(dim, seed, PaperSACSettings(**settings))
    if name == "random":
        return RandomProposer(dim, seed)
    if name == "sobol":
        from hmcore.agents.sobol import SobolProposer

        return SobolProposer(dim, seed)
    if name == "cmaes":
        from hmcore.agents.cmaes import CMAProposer

        return CMAProposer(dim, seed, workers)
    if name == "de":
        from hmcore.agents.de import DEProposer

        return DEProposer(dim, seed, budget, workers)
    if name == "bo":
        from hmcore.agents.bo import BOProposer

        return BOProposer(dim, seed)
    if name == "lm":
        from hmcore.agents.lm import LMDriver

        return LMDriver(dim, seed)
    if name == "esmda":
        from hmcore.agents.esmda import ESMDADriver

        return ESMDADriver(dim, seed)
    raise ValueError(f"agent must be one of {list(METHODS)}, got {name!r}")


def budget_problem(name: str, budget: int, workers: int) -> str | None:
    """Why ``budget`` / ``workers`` cannot run method ``name`` (None when they can)."""
    if name == "sac-paper" and budget % workers:
        return (f"sac-paper steps its {workers} env copies together: the budget {budget} must "
                f"be a multiple of the workers {workers} (e.g. "
                f"{max(workers, budget // workers * workers)})")
    if name == "esmda":
        from hmcore.agents.esmda import plan

        try:
            plan(budget)
        except ValueError as exc:
            return str(exc)
    return None


__all__ = ["ABLATIONS", "AGENTS", "DEFAULT_AGENT", "METHODS", "VERSIONS", "method_version", "Driver", "Feedback", "Proposal", "Proposer", "RandomProposer",
           "SACProposer", "SACSettings", "budget_problem", "make_proposer"]
