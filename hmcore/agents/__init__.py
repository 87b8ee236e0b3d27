"""Proposers (ask/tell): they never run the simulator; the caller evaluates what they ask."""

from hmcore.agents.base import Feedback, Proposal, Proposer
from hmcore.agents.random_search import RandomProposer
from hmcore.agents.sac import SACProposer, SACSettings


def make_proposer(name: str, dim: int, seed: int, **settings) -> Proposer:
    """Build a proposer by name: ``sac`` (reference method) or ``random`` (baseline)."""
    if name == "sac":
        return SACProposer(dim, seed, SACSettings(**settings))
    if name == "random":
        return RandomProposer(dim, seed)
    raise ValueError(f"agent must be one of ['sac', 'random'], got {name!r}")


__all__ = ["Feedback", "Proposal", "Proposer", "RandomProposer", "SACProposer", "SACSettings",
           "make_proposer"]
