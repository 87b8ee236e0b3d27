"""A case: base deck + measured well history + parameter space (+ misfit/simulator settings).

Read from TOML and validated with pydantic; every problem in the file, the deck and the
observed history is collected and raised together as one :class:`CaseError`::
    [case]
    name = "punqs3"
    deck = "PUNQS3.DATA"              # relative to this file, or absolute
    observed = "observed.csv"
    time_tolerance_days = 30          # default 30
    history_end_days = 2936           # optional: later rows are held back from fitting
                                      # (a TOML date such as 2001-01-01 works too)

    [misfit]                          # optional
    variant = "mean"                  # or "robust": mean + robust_lambda * worst well-response
    robust_lambda = 0.5
    objective = "likelihood"          # or "E": what a campaign minimises and selects by

    [simulator]                       # optional
    backend = "opm"                   # or a command template: "flow {deck} --output-dir={run_dir}"
    timeout_s = 900
    threads = 1                       # threads per run (a field-size deck: 2 or more)
    processes = 1                     # MPI processes per run: needs a command backend that
                                      # starts them, e.g. "mpirun -np {processes} flow {deck}
                                      # --output-dir={run_dir} --threads-per-process={threads}"
    stop_at_last_observation = false  # end every run at the report step of the last
                                      # observation: cheaper, but no forecast beyond it

    [physics]                         # optional (defaults shown; see hmcore.scoring.physics)
    perm_cap_ratio = 5.0              # largest cell permeability after multipliers, as a
                                      # multiple of the deck's own largest (per keyword) ...
    # perm_cap_md = 20000             # ... or an absolute cap in mD, when set
    poro_max = 0.6
    kv_kh_min = 0.001                 # per-cell kv/kh range ...
    kv_kh_max = 1.0
    kv_kh_max_fraction = 0.10         # ... share of cells that may newly leave it
    trend_sd = 3.0                    # distance from the deck's porosity-permeability trend ...
    trend_max_fraction = 0.02         # ... share of cells that may newly go beyond it
    pore_volume_change_max = 0.15     # relative change of the total pore volume
    # pressure_min = 1.01325          # lowest simulated BHP, deck units (default 1 atm)
    failure_penalty = 10.0
    violation_weight = 5.0            # P = weight * sum of the excesses

    [noise.WBHP]                      # optional: the measurement error, per quantity (and
    absolute = 2.0                    # per well: [noise.WBHP.wells.PRO-1]); absolute, or
    correlation_days = 60             # relative (+ relative_min); see hmcore.model.noise_section

    [[parameters]]                    # optional; default: the five reference parameters
    name = "permx_mult"
    kind = "multiply"
    keywords = ["PERMX"]
    low = 0.3
    high = 3.0

    # a [[parameters]] table with kind = "field" (PORO, PERMX... per active cell, and its
    # prior) and the [ensemble] section: see hmcore.model.case_fields
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from datetime import date, datetime
from functools import partial
from pathlib import Path
from typing import Literal

import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hmcore.eclipse.deck_info import DeckInfo, ParsedDeck
from hmcore.eclipse.history import controlled_mask
from hmcore.errors import CaseError, Problem
from hmcore.fields.ensemble import EnsembleSpec
from hmcore.fields.latent import LatentSpec
from hmcore.fields.spec import FieldSpec
from hmcore.model import case_fields
from hmcore.model.cluster import ClusterSettings
from hmcore.model.noise_section import (
    NoiseSection,
    QuantityNoise,
    noise_name_problems,
    valid_statements,
    zero_error_problems,
)
from hmcore.model.observed import inspect_observed
from hmcore.model.parameters import Parameter, ParameterSpace, reference_parameters
from hmcore.model.validation import (
    OPM_BACKENDS,
    deck_reference_problems,
    did_you_mean,
    parameter_problems,
    simulator_problems,
)
from hmcore.simulation.responses import QUANTITIES

BUILTIN_CASES = ("synthetic",)
"""Case names that stand for a case hmflow writes itself (:mod:`hmcore.cases` resolves them)."""
HELD_BACK_FRACTION = 0.25
"""The share of the record held back from fitting when nothing states where the fitted history
ends (a case without ``history_end_days``, ``hmflow init``'s suggestion, the generated cases):
the last quarter, so the fit is judged on what it did not see."""


def default_history_end(first_day: float, last_day: float,
                        held_back: float = HELD_BACK_FRACTION) -> float:
    """The day the fitted history ends when none is stated: the last ``held_back`` share of
    ``[first_day, last_day]`` (days since START) is held back."""
    return float(first_day) + (1.0 - held_back) * (float(last_day) - float(first_day))


class _Strict(BaseModel):
    """A section of the case file: no unknown key, no type coercion (``true`` is not a number,
    ``"yes"`` not a boolean), no ``inf`` or ``nan``."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, allow_inf_nan=False)


class CaseSection(_Strict):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    deck: str
    observed: str
    time_tolerance_days: float = Field(default=30.0, gt=0)
    history_end_days: float | date | None = None  # days after START, or a date


class MisfitSettings(_Strict):
    variant: Literal["mean", "robust"] = "mean"
    robust_lambda: float = Field(default=0.5, ge=0)
    objective: Literal["likelihood", "E"] = "likelihood"  # see hmcore.calibration.objective


class SimulatorSettings(_Strict):
    backend: str = "opm"
    timeout_s: float = Field(default=900.0, gt=0)
    threads: int = Field(default=1, ge=1, le=256)  # per run; workers x threads <= cores
    processes: int = Field(default=1, ge=1, le=1024)  # MPI processes per run (a command backend)

    @property
    def cores_per_run(self) -> int:
        return self.threads * self.processes
    stop_at_last_observation: bool = False  # end runs at the last observed day (no forecast)


class PhysicsSettings(_Strict):
    """Limits of the physics checks (see :mod:`hmcore.scoring.physics`) and the penalties."""

    perm_cap_md: float | None = Field(default=None, gt=0)  # None: relative to the deck
    perm_cap_ratio: float = Field(default=5.0, gt=1)
    poro_max: float = Field(default=0.6, gt=0, le=1)
    kv_kh_min: float = Field(default=0.001, gt=0)
    kv_kh_max: float = Field(default=1.0, gt=0)
    kv_kh_max_fraction: float = Field(default=0.10, ge=0, le=1)
    trend_sd: float = Field(default=3.0, gt=0)
    trend_max_fraction: float = Field(default=0.02, ge=0, le=1)
    pore_volume_change_max: float = Field(default=0.15, gt=0)
    pressure_min: float | None = Field(default=None, ge=0)  # deck units; None: 1 atmosphere
    failure_penalty: float = Field(default=10.0, gt=0)
    violation_weight: float = Field(default=5.0, ge=0)


class CaseFile(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    case: CaseSection
    misfit: MisfitSettings = MisfitSettings()
    simulator: SimulatorSettings = SimulatorSettings()
    physics: PhysicsSettings = PhysicsSettings()
    parameters: tuple[case_fields.ParameterEntry, ...] | None = None
    ensemble: EnsembleSpec = EnsembleSpec()
    latent: LatentSpec | None = None
    noise: dict[str, QuantityNoise] = {}
    cluster: ClusterSettings = ClusterSettings()


@dataclass(frozen=True)
class Case:
    """A validated case, ready to evaluate."""

    name: str
    source: Path
    deck: Path
    observed_path: Path
    observed: pd.DataFrame
    space: ParameterSpace
    info: DeckInfo
    time_tolerance_days: float
    history_end_days: float | None
    misfit: MisfitSettings
    simulator: SimulatorSettings
    physics: PhysicsSettings
    noise: NoiseSection = field(default_factory=dict)
    """The ``[noise]`` statements: quantity -> stated measurement error."""
    fields: tuple[FieldSpec, ...] = ()
    """The ``kind = "field"`` parameters (``space`` holds the scalar ones), a files prior's
    folder resolved against the case file."""
    ensemble: EnsembleSpec = field(default_factory=EnsembleSpec)
    """The ``[ensemble]`` section (its defaults when the file has none)."""
    cluster: ClusterSettings = field(default_factory=ClusterSettings)  # ``[cluster]``
    latent: LatentSpec | None = None
    """The ``[latent]`` section: a calibration moves the fields by their prior's modes
    (:mod:`hmcore.fields.latent`); None: the fields keep the deck's values there."""

    @property
    def informative(self) -> pd.DataFrame:
        """Observed rows that can tell models apart: all but those a well's history control
        fixes (the oil rate of a well on ORAT, say; see :mod:`hmcore.eclipse.history`)."""
        if "controlled" not in self.observed:
            return self.observed
        return self.observed[~self.observed.controlled.astype(bool)]

    @property
    def fit_observed(self) -> pd.DataFrame:
        """Rows used for fitting (days <= history_end_days when set; controlled rows left out)."""
        rows = self.informative
        if self.history_end_days is None:
            return rows
        return rows[rows.days <= self.history_end_days]

    @property
    def heldout_observed(self) -> pd.DataFrame:
        """Rows held back from fitting (empty when history_end_days is not set)."""
        rows = self.informative
        if self.history_end_days is None:
            return rows.iloc[0:0]
        return rows[rows.days > self.history_end_days]

    @property
    def stop_step(self) -> int | None:
        """The report step runs end at (None: the whole schedule)."""
        if not self.simulator.stop_at_last_observation:
            return None
        last = float(self.observed.days.max())
        days = self.info.report_days
        step = next((k for k, d in enumerate(days) if d >= last - 1e-6), len(days) - 1)
        return step if step < len(days) - 1 else None

    @property
    def run_end_days(self) -> float:
        """The last day a run simulates."""
        step = self.stop_step
        return self.info.end_days if step is None else self.info.report_days[step]

    def with_space(self, space: ParameterSpace) -> "Case":
        """The same case with another parameter space (checked against the deck)."""
        problems = deck_reference_problems(space.parameters, self.info, str(self.source))
        if problems:
            raise CaseError(problems)
        return Case(**{**self.__dict__, "space": space})


def case_file_name(path: Path) -> str:
    """The ``[case] name`` of a case TOML (cheap: no deck or history is read); ValueError when
    the file or the name is missing."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"case file {path} not found; give a TOML path or one of the built-in "
                         f"cases {BUILTIN_CASES}")
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"case file {path} cannot be read as TOML ({exc})") from exc
    name = (data.get("case") or {}).get("name")
    if not isinstance(name, str) or not name:
        raise ValueError(f"{path}: [case] name is missing")
    return name


def _parameters(cfg: CaseFile | None, data: dict
                ) -> tuple[tuple[Parameter, ...], list[tuple[int, FieldSpec]], bool]:
    """The case's scalar parameters (the reference five when the file gives no
    ``[[parameters]]``), its fields with their index in the list, and whether the file gives
    any; when the file has problems elsewhere, the entries that are valid by themselves, so
    that they are checked against the deck in the same pass."""
    raw = data.get("parameters")
    if (cfg.parameters if cfg is not None else raw) is None:
        return reference_parameters(), [], False
    entries = list(enumerate(cfg.parameters)) if cfg is not None else case_fields.valid_entries(raw)
    return (tuple(p for _, p in entries if isinstance(p, Parameter)),
            [(i, f) for i, f in entries if isinstance(f, FieldSpec)], True)


def _case_path(case: str | Path) -> Path:
    """The case file's absolute path; CaseError when the name cannot be a readable file."""
    text = str(case)
    if "\0" in text:
        raise CaseError([Problem(repr(text), "the case path contains a null byte",
                                 "give the case file's path as plain text")])
    try:
        path = Path(text).expanduser().resolve()
    except RuntimeError as exc:  # ~nosuchuser/...
        raise CaseError([Problem(text, f"the path cannot be expanded ({exc})",
                                 "give the path without ~user, or an existing user's")]) from exc
    if path.is_dir():
        raise CaseError([Problem(str(path), "is a folder, not a case file",
                                 "give the case TOML file inside it")])
    if not path.is_file():
        raise CaseError([Problem(str(path), "case file not found",
                                 f"give a TOML path or one of the built-in cases {BUILTIN_CASES}")])
    return path


def _read_toml(path: Path) -> dict:
    try:
        return tomllib.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise CaseError([Problem(str(path), f"not a text file in UTF-8 (byte {exc.start}: "
                                 f"{exc.reason})", "give the case TOML file (plain UTF-8 text)")]
                        ) from exc
    except OSError as exc:
        raise CaseError([Problem(str(path), f"cannot be read: {exc.strerror}",
                                 "check the file's permissions")]) from exc
    except tomllib.TOMLDecodeError as exc:
        raise CaseError([Problem(str(path), f"invalid TOML: {exc}",
                                 "fix the syntax at the line and column named")]) from exc


def load_case_file(case: str | Path) -> Case:
    """Load and validate a case file; raise CaseError with every problem found (a built-in
    case's name is resolved to its file by :func:`hmcore.cases.load_case`).

    The one validation pass before any simulator or Prefect start: the case file's keys and
    values, the deck (OPM's parser, INCLUDE files and cycles), the observed history, every
    parameter applied dry to the deck (:mod:`hmcore.model.validation`) and the simulator command."""
    path = _case_path(case)
    data = _read_toml(path)
    problems: list[Problem] = []
    cfg = None
    try:
        cfg = CaseFile.model_validate(data)
    except ValidationError as exc:
        problems += _validation_problems(exc, path)
    section = data.get("case") if isinstance(data.get("case"), dict) else {}
    deck_key, obs_key = section.get("deck"), section.get("observed")
    info = observed = None
    located: dict[str, Path] = {}
    for key, value in (("deck", deck_key), ("observed", obs_key)):
        if isinstance(value, str):
            try:
                located[key] = _relative_to(path, value)
            except ValueError as exc:
                problems.append(Problem(f"{path} key 'case.{key}'", str(exc),
                                        "give a plain path, relative to the case file or "
                                        "absolute"))
    deck, observed_path = located.get("deck"), located.get("observed")
    parsed: ParsedDeck | None = None
    if deck is not None:  # checked even when other keys are wrong: all problems at once
        try:
            info, parsed = DeckInfo.inspect_parsed(deck)
        except CaseError as exc:
            problems.extend(exc.problems)
    if observed_path is not None:
        observed, obs_problems = inspect_observed(
            observed_path, info.unit_system if info is not None else None,
            info.start if info is not None else None)
        problems.extend(obs_problems)
    params, fields, given = _parameters(cfg, data)
    names = [p.name for p in params] + [f.name for _, f in fields]
    if given and data.get("parameters") == []:
        problems.append(Problem(f"{path} key 'parameters'", "the [[parameters]] list is empty",
                                "add at least one [[parameters]] table, or remove the key to "
                                "use the five reference parameters"))
    dups = sorted({n for n in names if names.count(n) > 1})
    if dups:
        problems.append(Problem(f"{path} key 'parameters'", f"parameter name(s) {dups} are "
                                "given more than once", "give every parameter its own name"))
    backend = (data.get("simulator") or {}).get("backend") if isinstance(
        data.get("simulator"), dict) else None
    if isinstance(backend, str):  # checked even when other keys are wrong
        problems.extend(simulator_problems(backend, f"{path} key 'simulator.backend'"))
    processes = (data.get("simulator") or {}).get("processes") if isinstance(
        data.get("simulator"), dict) else None
    if (isinstance(processes, int) and processes > 1
            and (backend if isinstance(backend, str) else "opm") in OPM_BACKENDS):
        problems.append(Problem(
            f"{path} key 'simulator.processes'", f"{processes} MPI processes per run, but the "
            "built-in OPM Flow (pip opm-simulators) is built without MPI and runs one process",
            "start them with a command backend, e.g. backend = \"mpirun -np {processes} flow "
            "{deck} --output-dir={run_dir}\" (a command-line OPM Flow built with MPI), or set "
            "processes = 1 and use threads"))
    if info is not None:
        where = f"{path} [[parameters]]"
        deck_problems = deck_reference_problems(params, info, where)
        problems.extend(deck_problems)

        clean = [p for p in params if not any(x.where == f"{where} '{p.name}'"
                                              for x in deck_problems)]
        problems.extend(parameter_problems(clean, info, where))
    if isinstance(data.get("latent"), dict) and not fields:
        problems.append(Problem(f"{path} key 'latent'", "a [latent] section moves the fields "
                                "by their prior's modes, and the case has no field parameter",
                                "add a kind = \"field\" [[parameters]] table, or remove "
                                "[latent]"))
    if fields:
        ensemble = cfg.ensemble if cfg is not None else None
        problems.extend(case_fields.field_problems(path, fields, parsed, case_fields.ensemble_size(
            ensemble, data.get("ensemble")), partial(_relative_to, path)))
    if info is not None and observed is not None:
        problems.extend(_check_observed_against_deck(observed, info, observed_path))
    problems.extend(noise_name_problems(data.get("noise"), str(path),
                                        info.wells if info is not None else None))
    if observed is not None:
        problems.extend(zero_error_problems(valid_statements(data.get("noise")), str(path),
                                            observed))
    end = cfg.case.history_end_days if cfg else None
    if isinstance(end, date) and info is not None:
        end = (datetime.combine(end, datetime.min.time()) - info.start).total_seconds() / 86400
    if isinstance(end, (int, float)) and end <= 0:
        problems.append(Problem(f"{path} key 'case.history_end_days'", f"history_end_days="
                                f"{end:g} is not after the deck's START", "use a later day or "
                                "date, or remove the key"))
    first = (float(observed[~observed.derived].days.min()) if observed is not None
             and not observed.empty else None)
    if isinstance(end, (int, float)) and first is not None and 0 < end < first:
        problems.append(_before_first(path, end, first))
    if info is not None and end is not None and end > info.end_days:
        problems.append(Problem(f"{path} key 'case.history_end_days'",
                                f"history_end_days={end} is after the end of the schedule "
                                f"({info.end_days} days)", "use a day within the schedule or "
                                "remove the key"))
    if problems or cfg is None:
        raise CaseError(problems)
    observed = observed.assign(controlled=controlled_mask(observed, info.history))
    if observed.controlled.all():
        raise CaseError([Problem(str(observed_path), "every observed row is a rate or pressure "
                                 "that its well's history control fixes (WCONHIST/WCONINJH "
                                 "CMODE), so no row can tell models apart",
                                 "add the other phases' rates or the BHP of the wells")])
    informative = observed[~observed.controlled.astype(bool)]
    if end is not None and not (informative.days <= end).any():  # the rows before it: fixed
        raise CaseError([_before_first(path, end, float(informative.days.min()))])
    return Case(cfg.case.name, path, deck.resolve(), observed_path.resolve(), observed,
                ParameterSpace(parameters=tuple(params)), info, cfg.case.time_tolerance_days,
                end, cfg.misfit, cfg.simulator, cfg.physics, dict(cfg.noise),
                tuple(case_fields.resolved(f, partial(_relative_to, path)) for _, f in fields),
                cfg.ensemble.resolved([f for _, f in fields]), cfg.cluster, cfg.latent)


def _before_first(path: Path, end: float, first: float) -> Problem:
    return Problem(f"{path} key 'case.history_end_days'",
                   f"history_end_days={end:g} is before the first observation (day {first:g}) "
                   "that can tell models apart, so no observed row would be fitted (rows with "
                   "days <= history_end_days are fitted)",
                   f"use a day >= {first:g}, or remove the key")


def _relative_to(case_file: Path, value: str) -> Path:
    """``value`` as a path, relative to the case file's folder; ValueError when it cannot be
    one (a null byte, an unknown ~user)."""
    if "\0" in value:
        raise ValueError(f"the path {value!r} contains a null byte")
    try:
        p = Path(value).expanduser()
    except RuntimeError as exc:
        raise ValueError(f"the path {value!r} cannot be expanded ({exc})") from exc
    return p if p.is_absolute() else (case_file.parent / p)


_TYPE_TAGS = {"float", "int", "str", "bool", "date", "datetime", "none", "tuple",
              "list"} | case_fields.ENTRY_TAGS  # a union's types, a kind, a prior's source


def _validation_problems(exc: ValidationError, path: Path) -> list[Problem]:
    """One problem per key (a union's alternatives joined), with 'did you mean' for a
    mistyped key."""
    merged: dict[str, list[dict]] = {}
    for err in exc.errors():
        # a union's alternatives add their type ('float', 'list[...]') to the location; the
        # last item of an extra key's location is the user's key, whatever its name
        *path_items, last = err["loc"] or ("",)
        keep_last = err.get("type") == "extra_forbidden"
        loc = [x for x in (path_items if keep_last else [*path_items, last])
               if not (isinstance(x, str) and (x in _TYPE_TAGS or "[" in x))]
        if keep_last:
            loc.append(last)
        merged.setdefault(".".join(str(x) for x in loc), []).append(err)
    out = []
    for key, errs in merged.items():
        msgs = list(dict.fromkeys(_message(e) for e in errs))
        what = msgs[0] if len(msgs) == 1 else " or ".join(
            [msgs[0]] + [m.removeprefix("Input should be ") for m in msgs[1:]])
        out.append(Problem(f"{path} key '{key}'" if key else str(path), what,
                           _hint(errs[0], key)))
    return out


def _message(err: dict) -> str:
    msg = err["msg"]
    if err.get("type") == "value_error":
        msg = msg.removeprefix("Value error, ")
    if "input" in err and err.get("type") not in ("missing", "extra_forbidden", "value_error",
                                                  "model_type", "dict_type"):
        shown = repr(err["input"])
        msg += f", got {shown if len(shown) < 60 else shown[:57] + '...'}"
    return msg


def _hint(err: dict, key: str = "") -> str:
    if err.get("type") == "extra_forbidden":
        return "remove the key or check its spelling" + _near_key(key, err["loc"])
    if err.get("type") == "missing":
        return "add the key"
    if err.get("type") == "enum" and err["loc"][0] == "parameters" and key.endswith(".kind"):
        return case_fields.kind_hint(err.get("input"))
    return "see the rule stated above"


_SECTIONS = {"case": CaseSection, "misfit": MisfitSettings, "simulator": SimulatorSettings,
             "physics": PhysicsSettings, "ensemble": EnsembleSpec, "noise": QuantityNoise,
             "cluster": ClusterSettings, "latent": LatentSpec}
"""The section a key sits in -> its model (a ``[[parameters]]`` entry's model is known by its
kind, :func:`hmcore.model.case_fields.entry_choices`)."""


def _near_key(key: str, loc: tuple = ()) -> str:
    """' (did you mean 'case.history_end_days'?)' for a mistyped key (``loc``: pydantic's
    location of the error, which names a parameter's kind)."""
    parts = key.split(".")
    if len(parts) == 1:
        choices = list(CaseFile.model_fields)
    elif parts[0] == "parameters":
        choices = case_fields.entry_choices(tuple(loc))
    else:
        model = _SECTIONS.get(parts[0])
        choices = list(model.model_fields) if model is not None else []
    return did_you_mean(parts[-1], choices) if choices else ""


def _check_observed_against_deck(obs: pd.DataFrame, info: DeckInfo, path: Path) -> list[Problem]:
    problems = []
    measured = obs[~obs.derived]
    named = measured[measured.well != ""]  # an empty well is reported with the CSV's rows
    for well, grp in named[~named.well.isin(list(info.wells))].groupby("well"):
        problems.append(Problem(f"{path} {_lines(grp)}", f"unknown well '{well}'"
                                + _near([well], info.wells),
                                f"the deck's wells are {sorted(info.wells)}"))
    for q in sorted(set(obs.quantity) & set(QUANTITIES)):  # unknown ones are reported already
        if q not in info.keyword_names:
            rows = obs[obs.quantity == q]
            what = (f"the deck's SUMMARY section does not ask for {q}, so the simulator would "
                    f"report nothing to match {len(rows)} {q} row(s) against")
            if rows.derived.all():
                what += f" ({q} is derived from WOPR with {'WWCT' if q == 'WWPR' else 'WGOR'})"
            problems.append(Problem(f"{info.path} SUMMARY", what, f"add the line {q} followed by "
                                    "a line with / to the SUMMARY section"))
    late = measured[measured.days > info.end_days + 1e-6]
    if not late.empty:
        problems.append(Problem(f"{path} {_lines(late)}",
                                f"days {sorted(set(late.days))[:5]} after the end of the schedule "
                                f"({info.end_days} days)", "drop those rows or extend the deck"))
    return problems


def _near(unknown, known) -> str:
    return did_you_mean(unknown[0], known) if len(unknown) == 1 else ""


def _lines(df: pd.DataFrame, most: int = 8) -> str:
    """'line 5' or 'lines 5, 9, 12 (+3 more)'."""
    lines = [int(x) for x in df.line]
    word = "line " if len(lines) == 1 else "lines "
    return word + ", ".join(map(str, lines[:most])) + (f" (+{len(lines) - most} more)" if len(lines) > most else "")
