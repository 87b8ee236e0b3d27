"""Judging a diagnosis against the hidden truth: was the effect visible in the fitted history,
does an answer's cause name it (the same kind and well, layer, plane or box; a dated cause
within :data:`~hmcore.scenarios.generators.START_TOLERANCE_DAYS` of the start), right or wrong;
and the answer's :class:`Outcome` by the evidence (:func:`answer_outcome`): right when the
truth carries the dominant weight, honest when it is in the reported set of explanations the
data cannot separate, wrong otherwise.
"""

from __future__ import annotations

from enum import Enum

from hmcore.diagnosis.decision import heldout_decisive_drop
from hmcore.diagnosis.settings import DiagnosisSettings
from hmcore.scenarios.effects import HiddenEffect
from hmcore.scenarios.generators import START_TOLERANCE_DAYS
from hmcore.scoring.record_format import upgrade_diagnosis


class Outcome(str, Enum):
    """An answer judged by what it says (:func:`answer_outcome`)."""

    RIGHT = "right"
    """One explanation dominates, and it names the truth."""
    HONEST = "honest"
    """A set the data cannot separate, the truth in it."""
    WRONG = "wrong"
    """A single confident cause that is not the truth, or a set without it."""


# ----------------------------------------------------------------------------- scoring a finding
def visible(signal: dict | None) -> bool:
    """Can a diagnosis be asked to find the effect whose :func:`effect_signal` is ``signal``?
    When it shows in the fitted history beyond the score test's line once the globals absorb
    what they can (``visible_in_fitted_history``), or when it shows in the held-back history
    beyond the diagnosis's own held-back noise line (what the globals leave there, or all of it
    when the fitted history shows nothing for them to absorb): the calibrated model then
    misses the held-back history and the diagnosis takes the longer record (an effect that
    starts after the fitted window). No signal: visible (nothing says otherwise)."""
    s = signal or {}
    if s.get("visible_in_fitted_history", True):
        return True
    held = s.get("chi2_heldout_after_globals", s.get("chi2_heldout"))
    n = s.get("n_heldout_measured")
    return bool(held is not None and n and
                held >= heldout_decisive_drop(int(n), DiagnosisSettings()))


BOX_AGREEMENT = 0.25
"""Least Jaccard index (columns in both boxes over columns in either) at which a named region
is the hidden one (:func:`boxes_agree`)."""


def boxes_agree(a, b) -> bool:
    """Do two boxes of columns (i0, i1, j0, j1, ...; 1-based, inclusive) lie in the same
    place: do they share at least :data:`BOX_AGREEMENT` of the columns either covers? A 7x7
    box holding a 5x5 one (0.51), one moved 3 cells along one axis (0.40) or a 7x7 box sharing
    4 x 4 columns with a 5x5 one (0.28) do; a 7x7 box moved 3 cells along both axes (0.20), or
    centred on a well while a 9x9 one is centred 3 cells off it in i and j (0.24), do not. With
    a handful of wells the data locate a region to a few cells, not to the cell."""
    if a is None or b is None:
        return False
    di = min(a[1], b[1]) - max(a[0], b[0]) + 1
    dj = min(a[3], b[3]) - max(a[2], b[2]) + 1
    shared = max(di, 0) * max(dj, 0)
    size = lambda x: (x[1] - x[0] + 1) * (x[3] - x[2] + 1)  # noqa: E731
    return shared >= BOX_AGREEMENT * (size(a) + size(b) - shared)


def _box(cause: dict):
    """The box of a cause (its parameter's, in the cause's ``machine`` record)."""
    return (((cause.get("machine") or {}).get("parameter") or {}).get("box")
            or cause.get("box"))


def described(cause: dict, doc: dict) -> dict:
    """``cause`` with its ``machine`` record, from the diagnosis's ranked causes when it has
    none (an accepted or selected cause carries its id, not its parameter)."""
    if cause.get("machine"):
        return cause
    ranked = next((c for c in doc.get("causes") or [] if c.get("id") == cause.get("id")), {})
    return {**cause, "machine": ranked.get("machine")}


def names(cause: dict, effect: HiddenEffect) -> bool:
    """Does ``cause`` (a ranked or accepted cause of a diagnosis) name ``effect``? Its kind,
    and where the kind names one, the same well (well skin), place (regional permeability: the
    two boxes overlap, :func:`boxes_agree` - the ranking also tries boxes moved beside a well,
    so a well's name alone does not say where), layer (layer and vertical
    permeability) or candidate (fault plane, aquifer item, relperm table). A generated effect
    (:mod:`hmcore.scenarios.generators`), which no candidate matches exactly: its family,
    naming the wells it expects (``expect_wells``) and, where it lists them, being one of
    ``expect_ids`` (a partial fault: the library plane that parts the producers the same way),
    or for a region, its box as above. An effect whose ``expect_kinds`` list another family (a
    recompletion of no family: the productivity change) is named by a cause of that family too,
    with the wells and the start date it expects."""
    h = effect.candidate
    if cause["kind"] != h.kind and cause["kind"] not in (h.details.get("expect_kinds") or ()):
        return False
    start = h.details.get("start_day")
    if start is not None:  # a dated effect: the cause's start date too
        got = cause.get("start_day")
        if got is None or abs(float(got) - float(start)) > START_TOLERANCE_DAYS:
            return False
    if h.kind == "regional_permeability":  # where the box lies, not which well labels it
        return boxes_agree(_box(cause), h.parameter.box)
    if effect.generated:
        ids = h.details.get("expect_ids")
        return set(h.details.get("expect_wells") or []) <= set(cause["wells"]) and \
            (not ids or cause["id"] in ids)
    if h.kind == "well_skin":
        return cause["wells"] == list(h.wells)
    if h.kind in ("layer_permeability", "vertical_permeability"):
        return cause["layers"] == list(h.layers)
    return cause["id"] == h.id


def judge_effects(doc: dict, effects: list[HiddenEffect], signal: dict | None = None) -> dict:
    """Did the diagnosis ``doc`` find every hidden effect? One library effect (or none): as
    :func:`judge`. Otherwise each effect must be named (:func:`names`) by an accepted cause -
    an effect of no family (kind ``unexplained``) by the first cause, or by an accepted cause of
    a family its ``expect_kinds`` list - and, unless all are named as of no family, the
    held-back misfit must drop as in :func:`judge`. Returns ``found``,
    ``named`` (effect id -> bool), ``heldout_improved``, the ranking and the verdict."""
    if len(effects) <= 1 and not (effects and effects[0].generated):
        return judge(doc, effects[0] if effects else None, signal)
    accepted = doc.get("accepted") or ([doc["selected"]] if doc.get("selected") else [])
    first = doc["causes"][0]
    # an effect of no family the data hardly show: `none` is right too
    invisible = not visible(signal)
    no_family = ("unexplained", "none") if invisible else ("unexplained",)
    # (a cause names an effect of no family only through its expect_kinds)
    named = {e.candidate.id: ((e.kind == "unexplained" and first["kind"] in no_family)
                              or any(names(described(a, doc), e) for a in accepted))
             for e in effects}
    g = doc["gain"]
    held = g["heldout_after"] is not None and g["heldout_before"] is not None and \
        g["heldout_after"] < g["heldout_before"]
    truth_e = (signal or {}).get("truth_E_heldout")
    if not held and truth_e is not None and g["heldout_before"] is not None and \
            truth_e >= g["heldout_before"]:
        held = g.get("ssr_heldout_after") is not None and \
            g["ssr_heldout_after"] < g["ssr_heldout_before"]
    # an accepted cause must lower the held-back misfit, also one that names an effect of no
    # family through another family (expect_kinds) instead of `unexplained` first
    need_held = any(e.kind != "unexplained" or first["kind"] not in no_family for e in effects)
    top = [f"{c['id']} ({c['chi2']:.0f})" for c in doc["causes"][:4] if c["chi2"] is not None]
    found = bool(all(named.values()) and (held or not need_held))
    return {**answer_outcome(doc, effects, signal, found),
            "hidden": [e.candidate.id for e in effects], "named": named,
            "accepted": [a["id"] for a in accepted], "heldout_improved": bool(held),
            "found": found, "ranking": top, "verdict": doc["verdict"],
            "gain": {k: g[k] for k in ("fit_before", "fit_after", "heldout_before",
                                       "heldout_after")}}


def judge(doc: dict, effect: HiddenEffect | None, signal: dict | None = None) -> dict:
    """Did the diagnosis ``doc`` find the hidden ``effect`` (None: the control)?

    ``ranked_first``: the first cause has the hidden kind and, where the kind names one, the
    same well (well skin, regional permeability), layer (layer and vertical permeability) or
    candidate (fault plane, aquifer item, relperm table); ``selected``: the same candidate was
    accepted; ``heldout_improved``: the held-back misfit E (the issue's measure of the gain)
    went down - or, when the truth itself scores a held-back E no better than the calibrated
    base model (``signal["truth_E_heldout"]``, from :func:`effect_signal`: the noise decides E
    there, no diagnosis can lower it with the right answer), the noise-weighted held-back misfit
    (whitened SSR) went down; ``heldout_E_improved`` says what E did. For the control all
    three mean "reported none". ``found`` = all three.
    """
    first = doc["causes"][0]
    if doc.get("lead") and first["kind"] == "unexplained" and len(doc["causes"]) > 1:
        first = doc["causes"][1]  # a partial answer: as judge_effects, by what was accepted
    top = [f"{c['id']} ({c['chi2']:.0f})" for c in doc["causes"][:4] if c["chi2"] is not None]
    g = doc["gain"]
    if effect is None:
        ok = first["kind"] == "none" and doc["selected"] is None
        return {**answer_outcome(doc, [], signal, ok), "hidden": None, "ranked_first": ok, "selected": ok, "heldout_improved": ok,
                "found": ok, "ranking": top, "verdict": doc["verdict"]}
    h = effect.candidate
    same = names(first, effect)
    sel = doc["selected"] is not None and (  # the same candidate, or for a region the place
        doc["selected"]["id"] == h.id or (h.kind == "regional_permeability"
                                          and names(described(doc["selected"], doc), effect)))
    held_e = (g["heldout_after"] is not None and g["heldout_before"] is not None
              and g["heldout_after"] < g["heldout_before"])
    truth_e = (signal or {}).get("truth_E_heldout")
    e_cannot_tell = (truth_e is not None and g["heldout_before"] is not None
                     and truth_e >= g["heldout_before"])
    held = held_e or (e_cannot_tell and g.get("ssr_heldout_after") is not None
                      and g["ssr_heldout_after"] < g["ssr_heldout_before"])
    return {**answer_outcome(doc, [effect], signal, bool(same and sel and held)),
            "hidden": h.id, "value": effect.value, "ranked_first": bool(same),
            "selected": bool(sel), "heldout_improved": bool(held),
            "heldout_E_improved": bool(held_e), "truth_E_heldout": truth_e,
            "found": bool(same and sel and held), "ranking": top, "verdict": doc["verdict"],
            "gain": {k: g[k] for k in ("fit_before", "fit_after", "heldout_before",
                                       "heldout_after")}}


# ----------------------------------------------------------------------------- the answer
def _member(cid: str, doc: dict) -> dict:
    """The cause of an answer's member: the document's ranked cause of that id, or for
    ``none`` and ``unexplained`` (not always ranked) a bare one."""
    ranked = next((c for c in doc.get("causes") or [] if c.get("id") == cid), None)
    return ranked or {"id": cid, "kind": cid, "wells": [], "layers": [], "machine": None}


def answer_outcome(doc: dict, effects: list[HiddenEffect], signal: dict | None = None,
                   found: bool | None = None) -> dict:
    """The :class:`Outcome` of ``doc``'s answer (``doc["answer"]``: its members, one or the
    set) for the hidden ``effects`` (none: the control, whose truth is ``none``; an effect of
    no family: ``unexplained``, or ``none`` too when the data hardly show it). One library or
    generated effect is named as :func:`names` says; several effects by a pair (round 2's
    ``a+b``) whose causes name each; a document from before the answer was weighed
    (``derived``, see :func:`hmcore.scoring.record_format.upgrade_diagnosis`) takes ``found``:
    right or wrong.
    Returns ``outcome``, ``set_size`` and ``members``."""
    a = upgrade_diagnosis(doc)["answer"]
    members = list(a.get("members") or [])
    size = len(members)
    if a.get("derived"):
        out = Outcome.RIGHT if found else Outcome.WRONG
        return {"outcome": out.value, "set_size": max(size, 1), "members": members}
    no_family = ("unexplained", "none") if not visible(signal) else ("unexplained",)

    def named(effect: HiddenEffect, part: str) -> bool:
        cause = _member(part, doc)
        return ((effect.kind == "unexplained" and cause["kind"] in no_family)
                or names(described(cause, doc), effect))

    def holds(m: str) -> bool:  # a pair (round 2's "a+b") holds the truth when its causes do
        parts = m.split("+")
        if not effects:
            return len(parts) == 1 and _member(m, doc)["kind"] == "none"
        return all(any(named(e, part) for part in parts) for e in effects)

    hit = [holds(m) for m in members]
    out = (Outcome.RIGHT if size == 1 and hit[0] else
           Outcome.HONEST if size > 1 and any(hit) else Outcome.WRONG)
    return {"outcome": out.value, "set_size": size, "members": members}
