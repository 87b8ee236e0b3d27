"""Versioned artifact store (Parquet + manifests) and the evaluation journal of campaigns.

A plain library: it imports neither Prefect nor hmcore/tasks/flows.
"""

from .journal import EvaluationJournal, JournalConflictError
from .jsonable import canonical_json, sha256_json, to_jsonable
from .provenance import code_version
from .store import (
    DIAGNOSIS_RUNS,
    RUNS,
    ArtifactStore,
    ArtifactVersion,
    LinkRefusedError,
    refuse_links,
    validate_name,
)

__all__ = [
    "DIAGNOSIS_RUNS",
    "RUNS",
    "ArtifactStore",
    "ArtifactVersion",
    "EvaluationJournal",
    "JournalConflictError",
    "LinkRefusedError",
    "canonical_json",
    "code_version",
    "refuse_links",
    "sha256_json",
    "to_jsonable",
    "validate_name",
]
