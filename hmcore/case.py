"""A case: base deck + measured well history + parameter space (+ misfit/simulator settings).

Read from TOML and validated with pydantic; every problem in the file, the deck and the
observed history is collected and raised together as one :class:`CaseError`::

    [case]
    name = "punqs3"
    deck = "PUNQS3.DATA"              # relative to this file, or absolute
    observed = "observed.csv"
    time_tolerance_days = 30          # default 30
    history_end_days = 2936           # optional: later rows are held back from fitting

    [misfit]                          # optional
    variant = "mean"                  # or "robust": mean + robust_lambda * worst well-response
    robust_lambda = 0.5

    [simulator]                       # optional
    backend = "opm"                   # or a command template: "flow {deck} --output-dir={run_dir}"
    timeout_s = 900

    [physics]                         # optional (defaults shown; see hmcore.physics)
    perm_cap_md = 20000               # largest cell permeability after multipliers, mD
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

    [[parameters]]                    # optional; default: the five reference parameters
    name = "permx_mult"
    kind = "multiply"
    keywords = ["PERMX"]
    low = 0.3
    high = 3.0
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hmcore.deck_info import DeckInfo
from hmcore.errors import CaseError, Problem
from hmcore.observed import inspect_observed
from hmcore.parameters import Parameter, ParameterSpace, reference_parameters
from hmcore.responses import QUANTITIES

BUILTIN_CASES = ("synthetic",)


class _Strict(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class CaseSection(_Strict):
    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    deck: str
    observed: str
    time_tolerance_days: float = Field(default=30.0, gt=0)
    history_end_days: float | None = Field(default=None, gt=0)


class MisfitSettings(_Strict):
    variant: Literal["mean", "robust"] = "mean"
    robust_lambda: float = Field(default=0.5, ge=0)


class SimulatorSettings(_Strict):
    backend: str = "opm"
    timeout_s: float = Field(default=900.0, gt=0)


class PhysicsSettings(_Strict):
    """Limits of the physics checks (see :mod:`hmcore.physics`) and the penalties."""

    perm_cap_md: float = Field(default=20000.0, gt=0)
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


class CaseFile(_Strict):
    case: CaseSection
    misfit: MisfitSettings = MisfitSettings()
    simulator: SimulatorSettings = SimulatorSettings()
    physics: PhysicsSettings = PhysicsSettings()
    parameters: tuple[Parameter, ...] | None = None


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

    @property
    def fit_observed(self) -> pd.DataFrame:
        """Rows used for fitting (days <= history_end_days when set)."""
        if self.history_end_days is None:
            return self.observed
        return self.observed[self.observed.days <= self.history_end_days]

    @property
    def heldout_observed(self) -> pd.DataFrame:
        """Rows held back from fitting (empty when history_end_days is not set)."""
        if self.history_end_days is None:
            return self.observed.iloc[0:0]
        return self.observed[self.observed.days > self.history_end_days]

    def with_space(self, space: ParameterSpace) -> "Case":
        """The same case with another parameter space (checked against the deck)."""
        problems = _check_parameters(space.parameters, self.info, str(self.source))
        if problems:
            raise CaseError(problems)
        return Case(**{**self.__dict__, "space": space})


def case_name(case: str | Path) -> str:
    """The ``[case] name`` of a case TOML (cheap: no deck or history is read), or the name of a
    built-in case; ValueError when the file or the name is missing."""
    if str(case) in BUILTIN_CASES:
        return str(case)
    path = Path(case)
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


def resolve_case_path(case: str | Path) -> Path:
    """A TOML path as given, or the built-in case name ``synthetic`` (generated on first use)."""
    if str(case) == "synthetic":
        from hmcore.synthetic import ensure_synthetic_case

        return ensure_synthetic_case()
    return Path(case)


def load_case(case: str | Path) -> Case:
    """Load and validate a case; raise CaseError with every problem found."""
    path = resolve_case_path(case).resolve()
    if not path.is_file():
        raise CaseError([Problem(str(path), "case file not found",
                                 f"give a TOML path or one of the built-in cases {BUILTIN_CASES}")])
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise CaseError([Problem(str(path), f"invalid TOML: {exc}",
                                 "fix the syntax at the line and column named")]) from exc
    problems: list[Problem] = []
    cfg = None
    try:
        cfg = CaseFile.model_validate(data)
    except ValidationError as exc:
        problems += [Problem(f"{path} key '{'.'.join(str(x) for x in err['loc'])}'", err["msg"],
                             _hint(err)) for err in exc.errors()]
    section = data.get("case") if isinstance(data.get("case"), dict) else {}
    deck_key, obs_key = section.get("deck"), section.get("observed")
    info = observed = None
    deck = _relative_to(path, deck_key) if isinstance(deck_key, str) else None
    observed_path = _relative_to(path, obs_key) if isinstance(obs_key, str) else None
    if deck is not None:  # checked even when other keys are wrong: all problems at once
        try:
            info = DeckInfo.inspect(deck)
        except CaseError as exc:
            problems.extend(exc.problems)
    if observed_path is not None:
        observed, obs_problems = inspect_observed(observed_path)
        problems.extend(obs_problems)
    params = (cfg.parameters if cfg and cfg.parameters is not None else reference_parameters())
    if info is not None:
        problems.extend(_check_parameters(params, info, f"{path} [[parameters]]"))
    if info is not None and observed is not None:
        problems.extend(_check_observed_against_deck(observed, info, observed_path))
    end = cfg.case.history_end_days if cfg else None
    if info is not None and end is not None and end > info.end_days:
        problems.append(Problem(f"{path} key 'case.history_end_days'",
                                f"history_end_days={end} is after the end of the schedule "
                                f"({info.end_days} days)", "use a day within the schedule or "
                                "remove the key"))
    if problems or cfg is None:
        raise CaseError(problems)
    return Case(cfg.case.name, path, deck.resolve(), observed_path.resolve(), observed,
                ParameterSpace(parameters=tuple(params)), info, cfg.case.time_tolerance_days,
                cfg.case.history_end_days, cfg.misfit, cfg.simulator, cfg.physics)


def _relative_to(case_file: Path, value: str) -> Path:
    p = Path(value).expanduser()
    return p if p.is_absolute() else (case_file.parent / p)


def _hint(err: dict) -> str:
    if err.get("type") == "extra_forbidden":
        return "remove the key or check its spelling"
    if err.get("type") == "missing":
        return "add the key"
    return "see the rule stated above"


def _check_parameters(params, info: DeckInfo, where: str) -> list[Problem]:
    problems = []
    nx, ny, nz = info.dims
    for p in params:
        unknown = [w for w in p.wells if w not in info.wells]
        if unknown:
            problems.append(Problem(f"{where} '{p.name}'", f"unknown well(s) {unknown}",
                                    f"the deck's wells are {sorted(info.wells)}"))
        bad_layers = [k for k in p.layers if not 1 <= k <= nz]
        if bad_layers:
            problems.append(Problem(f"{where} '{p.name}'", f"layer(s) {bad_layers} outside 1..{nz}",
                                    "layers are 1-based k indices"))
        if p.box is not None:
            i1, i2, j1, j2, k1, k2 = p.box
            if i2 > nx or j2 > ny or k2 > nz:
                problems.append(Problem(f"{where} '{p.name}'", f"box {p.box} outside the grid "
                                        f"{nx}x{ny}x{nz}", "use 1-based indices inside the grid"))
        for kw in p.keywords:
            if kw.upper() in ("PORO", "PERMX", "PERMY", "PERMZ", "NTG") and \
                    kw.upper() not in info.properties:
                problems.append(Problem(f"{where} '{p.name}'", f"the deck defines no {kw}",
                                        "multiply a keyword the GRID section defines"))
    return problems


def _check_observed_against_deck(obs: pd.DataFrame, info: DeckInfo, path: Path) -> list[Problem]:
    problems = []
    measured = obs[~obs.derived]
    for well, grp in measured[~measured.well.isin(list(info.wells))].groupby("well"):
        problems.append(Problem(f"{path} {_lines(grp)}", f"unknown well '{well}'",
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


def _lines(df: pd.DataFrame, most: int = 8) -> str:
    """'line 5' or 'lines 5, 9, 12 (+3 more)'."""
    lines = [int(x) for x in df.line]
    word = "line " if len(lines) == 1 else "lines "
    return word + ", ".join(map(str, lines[:most])) + (f" (+{len(lines) - most} more)" if len(lines) > most else "")
