"""The calibration methods by name, without importing them: which exist, the default, the
version a campaign is bound to, the ablations of ``sac``, and a campaign's default name. Light
on purpose (no method library is imported), so that the flows and the CLI can name methods at
start-up; :func:`hmcore.calibration.methods.make_proposer` builds one.
"""

from __future__ import annotations

AGENTS = ("sac", "sac-paper", "random", "sobol", "cmaes", "de", "bo", "lm", "esmda")
DEFAULT_AGENT = "lm"
"""The method a campaign runs unless told otherwise: the winner of the equal-budget benchmark
(docs/benchmarks.md: how it was measured, and the method it replaced)."""
VERSIONS = {"sac": 1, "lm": 6, "esmda": 2}
"""A method whose proposals changed: campaigns are bound to the version that made their calls
(a resume under another version is refused; a benchmark names its campaigns after it).
``lm`` 2: speculative Jacobian columns beside each trial point; 3: no call on a point already
simulated, physics checks as the edge of the domain, restarts instead of stalls; 4: the
residuals of the case's objective, the noise refined from the best call at a descent's end;
5: restarts alternate near the best call and anywhere in the box; 6: after an accepted step,
Broyden's update of the Jacobian and W - 1 of its columns anew (the ones run beside the
trial), instead of all d.
``esmda`` 2: the residuals of the case's objective."""


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


def default_campaign_name(case_name: str, agent: str, seed: int) -> str:
    """CASE-AGENT-seedS; a method's later version is another campaign (CASE-sac-v2-seedS)."""
    version = method_version(agent) if agent in METHODS else 1
    tag = f"{agent}-v{version}" if version > 1 else agent
    return f"{case_name}-{tag}-seed{seed}"
