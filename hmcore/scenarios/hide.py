"""A case that hides an effect, and the verdict on a diagnosis of it: what ``hmflow hide`` and
``hmflow reveal`` do.

* :func:`hide_problems`: every reason a request cannot be written, before anything is drawn
  or simulated (spelled as ``hmflow hide``'s options, which are the request's fields).
* :func:`hide_case`: take the effect asked for (a library candidate and value) or draw it of a
  kind (a library kind or a generator of effects beyond the library; none: a control,
  nothing hidden), write the built-in synthetic case of the seed or a case on a deck with it
  hidden in the truth run (:mod:`hmcore.scenarios.hidden`), and name the case after its
  folder. A request refused on the way leaves nothing half-written behind.
* :func:`reveal`: the hidden effects of a case against a diagnosis of it
  (:func:`hmcore.scenarios.judge.judge_effects`).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from hmcore.diagnosis.candidate import KINDS
from hmcore.eclipse.deck_info import DeckInfo
from hmcore.model.deck_values import base_values
from hmcore.model.parameters import ParameterSpace
from hmcore.scenarios.effects import HiddenEffect, chosen_effect, load_hidden_effects
from hmcore.scenarios.generators import GENERATORS, draw_effect, draw_effects
from hmcore.scenarios.hidden import (
    synthetic_deck_info,
    write_hidden_deck_case,
    write_hidden_synthetic_case,
)
from hmcore.scenarios.judge import judge_effects
from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH

HIDDEN_JSON = "hidden_effect.json"
"""The record of what a case hides (beside its case.toml): the effects, the truth, the signal."""


@dataclass(frozen=True)
class HiddenCase:
    """A case written by :func:`hide_case`."""

    case_toml: Path
    hidden_json: Path
    effect: HiddenEffect | None
    """The (first) hidden effect; None: a control, nothing hidden."""
    n_effects: int
    generator: str | None
    """The generator that drew the effects (beyond the library's geometry), else None."""
    signal: dict | None
    """How strongly the effect shows in the data (:func:`hmcore.scenarios.hidden.effect_signal`)."""


def hide_problems(out: Path, *, kind: str | None = None, candidate: str | None = None,
                  value: float | None = None, deck: Path | None = None,
                  globals_given: bool = False, record_end_days: float | None = None
                  ) -> list[str]:
    """Every reason the request cannot be written ([] when it can): ``out`` must be new or an
    empty directory, ``kind`` a library kind or a generator, ``candidate`` (a library
    candidate id, ``kind:detail``) of ``kind`` and not with a generator, ``value`` only with
    a ``candidate``, ``deck`` a file; the truth's global values (``globals_given``) and
    ``record_end_days`` only with a ``deck`` (the synthetic case has its own known truth)."""
    problems = []
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        problems.append(f"--out {out}: exists and is not an empty directory; nothing is "
                        "overwritten, choose a new one")
    if kind is not None and kind not in KINDS + GENERATORS:
        problems.append(f"--kind {kind!r}: unknown; one of {list(KINDS)} or a generator "
                        f"{list(GENERATORS)}, or 'field' with --case")
    if kind in GENERATORS and candidate is not None:
        problems.append(f"--candidate names a library candidate; --kind {kind} generates "
                        "effects beyond the library: give one of them, not both")
    if candidate is not None and kind is not None and not candidate.startswith(kind + ":"):
        problems.append(f"--candidate {candidate!r} is not of --kind {kind!r}")
    if value is not None and candidate is None:
        problems.append("--value needs --candidate (which parameter it is the value of)")
    if deck is not None and not deck.is_file():
        problems.append(f"--deck {deck}: no such file")
    if deck is None and (globals_given or record_end_days is not None):
        problems.append("--set and --record-end apply to --deck cases (the synthetic case has "
                        "its own known truth)")
    return problems


def hide_case(out: Path, *, seed: int = 0, kind: str | None = None,
              candidate: str | None = None, value: float | None = None,
              deck: Path | None = None, globals_: Mapping[str, float] | None = None,
              history_end_days: float | None = None, record_end_days: float | None = None,
              with_sigma: bool = False) -> HiddenCase:
    """Write into ``out`` a case whose measured history hides the effect asked for.

    ``seed`` draws the effect, its strength and the noise (and, for the synthetic case, the
    fields). ``candidate`` with ``value`` hides that library candidate; otherwise one effect
    is drawn of ``kind`` (or of the candidate's kind, among that candidate alone), or several
    by a generator; neither: the control. ``deck`` (default: the built-in synthetic reservoir
    of ``seed``) with ``globals_`` (the five global parameters in the truth, default the
    deck's own values) and ``record_end_days`` (the measured record's last day, default the
    schedule's end). ``history_end_days`` ends the fitted history (default 75 % of the
    record); ``with_sigma`` writes the noise sigma into the CSV (deck cases). Raises
    ValueError for an effect the deck cannot hold, after removing what it wrote."""
    created = not out.exists()
    try:
        return _write(out, seed, kind, candidate, value, deck, dict(globals_ or {}),
                      history_end_days, record_end_days, with_sigma)
    except ValueError:
        if created:  # leave nothing half-written behind
            shutil.rmtree(out, ignore_errors=True)
        raise


def _write(out: Path, seed: int, kind: str | None, candidate: str | None,
           value: float | None, deck: Path | None, globals_: dict[str, float],
           history_end_days: float | None, record_end_days: float | None,
           with_sigma: bool) -> HiddenCase:
    space = ParameterSpace.reference()
    if deck is None:
        truth = dict(SYNTHETIC_TRUTH)
        info = synthetic_deck_info(seed, out / "base-deck")
    else:
        info = DeckInfo.inspect(deck.resolve())
        truth = {**base_values(info, space), **globals_}
    effect = None
    k = kind or (candidate.split(":", 1)[0] if candidate else None)
    if candidate is not None and value is not None:
        effect = chosen_effect(candidate, value, info, space, truth)
    elif k in GENERATORS:
        draw_effects(k, seed, info, space, truth)  # an impossible one refused here
    elif k is not None:
        effect = draw_effect(k, seed, info, space, truth,
                             choices=[candidate] if candidate else None)
    generated = k if k in GENERATORS else None
    if deck is None:
        case_toml, effect = write_hidden_synthetic_case(
            out, seed, kind=generated, effect=effect, history_end_days=history_end_days)
        text = case_toml.read_text().replace('name = "synthetic"', f'name = "{out.name}"', 1)
        case_toml.write_text(text)
    else:
        case_toml, effect = write_hidden_deck_case(
            out, deck, seed, truth=truth, kind=generated, effect=effect,
            history_end_days=history_end_days, with_sigma=with_sigma, name=out.name,
            end_days=record_end_days)
    hidden_json = out / HIDDEN_JSON
    doc = json.loads(hidden_json.read_text())
    return HiddenCase(case_toml=case_toml, hidden_json=hidden_json, effect=effect,
                      n_effects=len(doc.get("effects") or []), generator=generated,
                      signal=doc.get("signal"))


@dataclass(frozen=True)
class Revealed:
    """A diagnosis judged against what its case hides (:func:`reveal`)."""

    effects: tuple[HiddenEffect, ...]
    diagnosis: dict
    """The diagnosis.json document."""
    signal: dict | None
    verdict: dict
    """:func:`~hmcore.scenarios.judge.judge` (one library effect or none) or
    :func:`~hmcore.scenarios.judge.judge_effects` (:attr:`several`)."""

    @property
    def several(self) -> bool:
        """Judged effect by effect: more than one effect hidden, or a generated one."""
        return len(self.effects) > 1 or bool(self.effects and self.effects[0].generated)

    @property
    def found(self) -> bool:
        return bool(self.verdict["found"])


def reveal(hidden: Path, diagnosis: Path) -> Revealed:
    """Judge the diagnosis.json at ``diagnosis`` against the ``hidden_effect.json`` of its
    case: right kind and place ranked first, selected, held-back misfit improved."""
    effects = tuple(load_hidden_effects(hidden))
    doc = json.loads(diagnosis.read_text())
    signal = json.loads(hidden.read_text()).get("signal")
    return Revealed(effects=effects, diagnosis=doc, signal=signal,
                    verdict=judge_effects(doc, list(effects), signal))
