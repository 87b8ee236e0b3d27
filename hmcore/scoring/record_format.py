"""The one home of journal-record format upgrades: what a record journaled by an older hmflow
lacks, derived from what it has, so that a campaign stored before a change still resumes and
reports.

* ``failure``: records journaled before failure kinds were stored carry the kind as the first
  word of their ``reason``.

And of a stored diagnosis document (``diagnosis.json``):

* ``answer``: diagnoses made before the explanations were weighed by their evidence (issue 46)
  name one cause, their first: :func:`upgrade_diagnosis` derives that answer, marked
  ``derived`` (no weights), so that ``reveal`` and the sweep judge them as they were judged.
"""

from __future__ import annotations

from hmcore.errors import FailureKind

FAIL = "FAIL"  # hmcore.scoring.evaluation.Status.FAIL's value


def failure_of(record: dict) -> FailureKind | None:
    """A record's failure kind: its ``failure`` field, or for an older failed record the first
    word of its reason (an unknown word: a crash); None for a call that did not fail."""
    if record.get("failure"):
        return FailureKind(record["failure"])
    if record.get("status") != FAIL:
        return None
    head = str(record.get("reason", "")).split(":")[0].strip()
    return FailureKind(head) if head in {k.value for k in FailureKind} else FailureKind.CRASH


def upgrade(record: dict) -> dict:
    """``record`` in today's format (a new dict; the stored record is never rewritten)."""
    out = dict(record)
    if out.get("status") == FAIL and not out.get("failure"):
        kind = failure_of(out)
        out["failure"] = kind.value if kind is not None else None
    return out


def upgrade_diagnosis(doc: dict) -> dict:
    """A diagnosis document in today's format (a new dict when changed; the stored file is
    never rewritten): an older one gets the ``answer`` it gave - its first cause, alone,
    ``derived`` (no weights, no separations)."""
    if doc.get("answer"):
        return doc
    first = (doc.get("causes") or [{}])[0].get("id")
    return {**doc, "answer": {"kind": "single", "members": [first] if first else [],
                              "derived": True, "explanations": [], "separations": [],
                              "text": ""}}
