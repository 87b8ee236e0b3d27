"""A starting case for a deck hmflow has never seen: what ``hmflow init`` writes.

From the deck (read with OPM's parser): the wells and their types, the schedule, the unit
system, the faults; the measured history from the deck's own ``WCONHIST`` / ``WCONINJH``
records (:mod:`hmcore.eclipse.history`), or from a summary file (history vectors ``WOPRH``... when it
has them, else the plain vectors) or an observed CSV the user already has. Writes

* ``<name>_observed.csv`` - ``well, days, date, quantity, value, units`` in the deck's units;
* ``<name>.toml`` - the case, with the default parameter space active (porosity and
  permeability multipliers, producer skin) and per-well skins, per-fault multipliers,
  per-region permeability multipliers (MULTNUM, FLUXNUM, OPERNUM in GRID), critical-saturation
  shifts and aquifer strength written out but commented, ready to switch on.

Nothing existing is overwritten. Every history record that could not be used is returned with
its reason.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import numpy as np
import pandas as pd
import tomlkit

from hmcore.eclipse.deck_info import DeckInfo
from hmcore.eclipse.history import WellKind
from hmcore.errors import CaseError, Problem
from hmcore.model.case import default_history_end
from hmcore.model.parameters import MULTIREG_REGIONS, Parameter
from hmcore.ordering import natural_key
from hmcore.simulation.responses import QUANTITIES
from hmcore.simulation.rsm import read_rsm
from hmcore.units import DIMENSION_OF, Dimension, convert, deck_unit

OBSERVED_COLUMNS = ["well", "days", "date", "quantity", "value", "units"]


@dataclass(frozen=True)
class StartingCase:
    name: str
    info: DeckInfo
    observed: pd.DataFrame
    source: str
    skipped: tuple[str, ...]
    parameters: tuple[Parameter, ...]
    optional: tuple[Parameter, ...]

    def wells_by_kind(self) -> dict[str, list[str]]:
        injectors = {iv.well for iv in self.info.history.intervals
                     if iv.kind is WellKind.INJECTOR}
        kinds: dict[str, list[str]] = {"producer": [], "injector": []}
        for name, well in self.info.wells.items():
            kinds["producer" if well.producer and name not in injectors else "injector"].append(name)
        return {k: sorted(v, key=natural_key) for k, v in kinds.items()}


def observed_from_history(info: DeckInfo) -> pd.DataFrame:
    table = info.history.observed_table()
    return _finish(table[["well", "days", "quantity", "value"]], info)


def observed_from_summary(path: Path, info: DeckInfo) -> tuple[pd.DataFrame, tuple[str, ...]]:
    """Well vectors of a summary file (``.SMSPEC`` with its ``.UNSMRY``, or an ``.RSM`` text
    summary): ``WOPRH``-style history vectors when present (what a production-database export
    or a history-mode run holds), else the plain vectors; values in the deck's units (an RSM's
    own units are converted, or refused by name)."""
    smry, file_units = _summary(path, info)
    keys = set(smry.keys())
    history = {k.split(":")[0][:-1] for k in keys if ":" in k and k.split(":")[0].endswith("H")}
    days = np.round(np.asarray(smry.days if file_units is not None else smry["TIME"],
                               dtype=float), 2)
    frames, skipped, problems = [], [], []
    if history:  # measured vectors only: the plain ones are a simulation's
        unmatched = sorted(set(QUANTITIES) - history)
        plain = sorted({k.split(":")[0] for k in keys if ":" in k} & set(unmatched))
        if plain:
            skipped.append(f"{path}: {plain} have no history vector (...H) here; the plain "
                           "vectors are simulated values, not measurements: left out")
    for well in sorted(info.wells, key=natural_key):
        for q in QUANTITIES:
            key = (f"{q}H:{well}" if q in history else "") if history else f"{q}:{well}"
            if key not in keys:
                continue
            values = np.asarray(smry[key], dtype=float)
            if file_units is not None and not file_units[key].strip():
                if DIMENSION_OF[q] is not Dimension.FRACTION:
                    skipped.append(f"{path}: column {key} names no unit: read in the deck's "
                                   f"{deck_unit(q, info.unit_system)}")
            elif file_units is not None:
                try:
                    values = convert(values, q, file_units[key], info.unit_system)
                except ValueError as exc:
                    problems.append(Problem(f"{path}: column {key}", str(exc),
                                            f"give {q} in {deck_unit(q, info.unit_system)}"))
                    continue
            frames.append(pd.DataFrame({"well": well, "days": days, "quantity": q,
                                        "value": values}))
    if problems:
        raise CaseError(problems)
    other = sorted({k.split(":")[1] for k in keys if ":" in k and k.startswith("W")}
                   - set(info.wells))
    if other:
        skipped.append(f"{path}: wells {other[:10]} are not in the deck")
    if not frames:
        raise CaseError([Problem(str(path), "no well vector to import (looked for "
                                 + ("WOPRH, WBHPH..." if history else "WOPR, WBHP...") + ")",
                                 "export well rates and pressures into the summary")])
    table = pd.concat(frames, ignore_index=True)
    table = table[(table.days > 0) & (table.days <= info.end_days + 1e-6) & table.value.notna()]
    steps = np.round(info.report_days, 2)
    steps = steps[(steps > 0) & (steps <= table.days.max())]
    if len(steps) and np.isin(steps, table.days.unique()).mean() >= 0.9:
        # written on this schedule by a simulator: its own time steps between the report
        # steps are not measurements (a database export on its own dates is kept whole)
        table = table[np.isin(table.days, steps)]
    closed = (table.quantity == "WBHP") & (table.value <= 0)  # the well not open yet (or shut)
    for well, n in table[closed].groupby("well").size().items():
        skipped.append(f"{path}: {n} WBHP value(s) of {well} are 0 (well not open): left out")
    return _finish(table[~closed], info), tuple(skipped)


def _summary(path: Path, info: DeckInfo):
    """(summary, units per key): an RSM file's own units, or None for a binary summary (in
    the deck's units, as the simulator wrote it)."""
    if path.suffix.lower() == ".rsm":
        rsm = read_rsm(path, info.start)
        return rsm, rsm.units
    from opm.io.ecl import ESmry

    try:
        return ESmry(str(path)), None
    except Exception as exc:  # opm.io raises RuntimeError/ValueError on a bad file
        raise CaseError([Problem(str(path), f"cannot read the summary file: {exc}",
                                 "give the .SMSPEC of a summary (with its .UNSMRY beside it), "
                                 "or an .RSM text summary")])


def _finish(table: pd.DataFrame, info: DeckInfo) -> pd.DataFrame:
    out = table.copy()
    out["date"] = [(info.start + timedelta(days=float(d))).date().isoformat() for d in out.days]
    out["units"] = [deck_unit(q, info.unit_system) for q in out.quantity]
    order = sorted(range(len(out)), key=lambda i: (natural_key(str(out.well.iat[i])),
                                                   out.quantity.iat[i], out.days.iat[i]))
    return out.iloc[order][OBSERVED_COLUMNS].reset_index(drop=True)


def default_parameters(info: DeckInfo) -> tuple[Parameter, ...]:
    """The reference method's globals the deck can take, plus one skin on the producers."""
    out = []
    if "PORO" in info.properties:
        out.append(Parameter(name="poro_mult", kind="multiply", keywords=("PORO",), low=0.8,
                             high=1.2, description="global porosity multiplier"))
    for kw in ("PERMX", "PERMY", "PERMZ"):
        if kw in info.properties:
            out.append(Parameter(name=f"{kw.lower()}_mult", kind="multiply", keywords=(kw,),
                                 low=0.3, high=3.0, description=f"global {kw} multiplier"))
    if info.producers:
        out.append(Parameter(name="skin", kind="skin", low=-5.0, high=15.0,
                             description="skin on every producer connection"))
    return tuple(out)


def optional_parameters(info: DeckInfo) -> tuple[Parameter, ...]:
    """Per-well skins and per-fault multipliers, written commented out."""
    out = [Parameter(name=f"skin_{w}", kind="skin", wells=(w,), low=-5.0, high=15.0,
                     description=f"skin of {w}")
           for w in sorted(info.wells, key=natural_key)]
    out += [Parameter(name=f"fault_{_slug(f)}", kind="fault", faults=(f,), low=0.0, high=1.0,
                      description=f"transmissibility multiplier of fault {f}")
            for f in info.faults]
    for keyword, numbers in info.regions.items():
        if keyword in MULTIREG_REGIONS and keyword in info.grid_keywords and len(numbers) > 1:
            out += [Parameter(name=f"perm_{keyword.lower()}_{n}", kind="multiply",
                              keywords=tuple(k for k in ("PERMX", "PERMY", "PERMZ")
                                             if k in info.properties),
                              region=keyword, region_numbers=(n,), low=0.3, high=3.0,
                              description=f"permeability multiplier of {keyword} region {n}")
                    for n in numbers]
    for table, what in (("SWOF", "SWCR"), ("SWFN", "SWCR"), ("SGOF", "SGCR"), ("SGFN", "SGCR")):
        if table in info.keyword_names:
            out.append(Parameter(name=f"{what.lower()}_shift", kind="relperm", keywords=(table,),
                                 item=2, mode="endpoint", low=0.0, high=0.1,
                                 description=f"{what}: raise the critical saturation of "
                                 f"{table} column 2 (a lower one needs table rows below it)"))
    for keyword, item, what, low, high in (("AQUCT", 4, "aquifer permeability", 0.1, 10.0),
                                           ("AQUFETP", 4, "aquifer volume", 0.1, 10.0)):
        if keyword in info.keyword_names:
            out.append(Parameter(name=f"{keyword.lower()}_mult", kind="item_multiply",
                                 keywords=(keyword,), item=item, low=low, high=high,
                                 description=f"{what} multiplier ({keyword} item {item})"))
    return tuple(out)


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_]+", "_", name).strip("_") or "fault"


def starting_case(deck: Path, name: str, observed_csv: Path | None = None,
                  summary: Path | None = None) -> StartingCase:
    """Everything ``hmflow init`` writes, read from ``deck`` (and a summary or CSV)."""
    info = DeckInfo.inspect(Path(deck))
    skipped: tuple[str, ...] = info.history.skipped
    if observed_csv is not None:
        observed, source = pd.DataFrame(columns=OBSERVED_COLUMNS), str(observed_csv)
    elif summary is not None:
        observed, extra = observed_from_summary(Path(summary), info)
        source, skipped = str(summary), skipped + extra
    else:
        observed = observed_from_history(info)
        source = f"WCONHIST/WCONINJH records of {info.path.name}"
        if observed.empty:
            raise CaseError([Problem(str(info.path), "the deck holds no measured history (no "
                                     "WCONHIST or WCONINJH record on an open well)",
                                     "give the measured data with --summary FILE.SMSPEC or "
                                     "--observed FILE.csv")])
    return StartingCase(name, info, observed, source, skipped, default_parameters(info),
                        optional_parameters(info))


def case_toml(start: StartingCase, case_path: Path, observed_path: Path) -> str:
    """The case file's text (written with tomlkit, comments included)."""
    info = start.info
    doc = tomlkit.document()
    doc.add(tomlkit.comment(f"hmflow case written by `hmflow init` from {info.path}"))
    doc.add(tomlkit.comment(f"units: {info.unit_system} (the observed file is in them too)"))
    kinds = start.wells_by_kind()
    for kind, wells in kinds.items():
        if wells:
            doc.add(tomlkit.comment(f"{kind}s ({len(wells)}): {', '.join(wells)}"))
    doc.add(tomlkit.comment(f"schedule: {info.start.date()} + {info.end_days:g} days, "
                            f"{len(info.report_days) - 1} report steps"))
    if info.faults:
        doc.add(tomlkit.comment(f"faults: {', '.join(info.faults)}"))
    doc.add(tomlkit.nl())
    case = tomlkit.table()
    case.add("name", start.name)
    case.add("deck", _relative(info.path, case_path.parent))
    case.add("observed", _relative(observed_path, case_path.parent))
    case["observed"].comment(f"from {start.source}")
    case.add("time_tolerance_days", 30)
    case.add(tomlkit.comment("hold back the last quarter of the record to judge forecasts:"))
    end = round(default_history_end(0.0, info.end_days))
    case.add(tomlkit.comment(f"history_end_days = {end:g}"))
    doc.add("case", case)
    params = tomlkit.aot()
    for p in start.parameters:
        params.append(_parameter_table(p))
    doc.add("parameters", params)
    text = tomlkit.dumps(doc)
    if start.optional:
        extra = tomlkit.document()
        opt = tomlkit.aot()
        for p in start.optional:
            opt.append(_parameter_table(p))
        extra.add("parameters", opt)
        text += ("\n# More parameters, off until you remove the '# ' in front of a block:\n"
                 + "".join(f"# {line}\n" if line else "#\n"
                           for line in tomlkit.dumps(extra).strip().splitlines()))
    return text


def _parameter_table(p: Parameter) -> tomlkit.items.Table:
    t = tomlkit.table()
    data = p.model_dump(exclude_defaults=True)
    for key in ("name", "kind", "keywords", "wells", "faults", "region", "region_numbers",
                "item", "mode", "low", "high", "description"):
        if key in data:
            t.add(key, list(data[key]) if isinstance(data[key], tuple) else data[key])
    return t


def _relative(path: Path, base: Path) -> str:
    """Relative to the case file when it sits beside it or one folder up, else absolute."""
    path = Path(path).resolve()
    try:
        rel = os.path.relpath(path, Path(base).resolve())
    except ValueError:  # another drive
        return str(path)
    return rel if Path(rel).parts.count("..") <= 1 else str(path)


def write_starting_case(start: StartingCase, case_path: Path,
                        observed_csv: Path | None = None) -> tuple[Path, Path]:
    """Write the observed CSV (unless the user's own is given) and the case file; never
    overwrite (FileExistsError naming the file)."""
    case_path = Path(case_path)
    observed_path = (Path(observed_csv) if observed_csv is not None
                     else case_path.with_name(f"{case_path.stem}_observed.csv"))
    targets = [case_path] + ([] if observed_csv is not None else [observed_path])
    for target in targets:
        if target.exists():
            raise FileExistsError(f"{target} exists; hmflow init never overwrites (choose "
                                  "another --out or move the file)")
    case_path.parent.mkdir(parents=True, exist_ok=True)
    if observed_csv is None:
        with open(observed_path, "x") as fh:
            start.observed.to_csv(fh, index=False, float_format="%.6g")
    with open(case_path, "x") as fh:
        fh.write(case_toml(start, case_path, observed_path))
    return case_path, observed_path
