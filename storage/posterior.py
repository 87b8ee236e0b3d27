"""Where a campaign keeps its posterior draws in the store (:mod:`tasks.posterior`):
``<campaign>/posterior/vN/draws.json`` and the journal of version N's runs,
``evaluations-posterior-NNNN/``."""

POSTERIOR_STEP = "posterior"


def journal_name(version: int) -> str:
    """The journal of the runs of the ``posterior`` artifact's version ``version``."""
    return f"{POSTERIOR_STEP}-{version:04d}"
