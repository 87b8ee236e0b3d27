"""The measured history a deck carries itself: its ``WCONHIST`` and ``WCONINJH`` records.

A history-matching deck states each well's measured rates in the schedule: ``WCONHIST`` for
producers (oil, water, gas rates, the BHP when given) and ``WCONINJH`` for injectors (the
injected rate and BHP). A record holds from the report step where it appears until the next
record for that well; the simulator reports the rates of an interval at its end, so each
interval in history mode gives one observation per quantity at its end day.

A well in history mode is controlled by one of these rates (``CMODE``): the simulated value of
that quantity equals the measured one by construction, so it carries no information about the
model. :func:`controlled_mask` marks such rows so the misfit leaves them out.

Walks the deck as OPM's parser read it (``INCLUDE`` files expanded, ``N*`` defaults applied):
``'*'`` names every well, ``'PROD*'`` a pattern; a defaulted rate is 0; ``WELOPEN`` shuts and
opens wells (no rows while shut); ``WCONPROD``/``WCONINJE`` end a well's history mode; a well
list (``'*LIST'``) names the wells ``WLIST`` put in it up to that record (NEW, ADD, DEL, MOV).
Not read: keywords inside ``ACTIONX`` (taken as unconditional).
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import pandas as pd

# producer control mode -> the quantity it fixes (LRAT and RESV fix no single phase rate)
PRODUCER_CONTROLLED = {"ORAT": "WOPR", "WRAT": "WWPR", "GRAT": "WGPR", "BHP": "WBHP"}
INJECTED = {"WATER": "WWIR", "WAT": "WWIR", "GAS": "WGIR"}


class WellKind(str, Enum):
    PRODUCER = "producer"
    INJECTOR = "injector"


@dataclass(frozen=True)
class Interval:
    """One report interval ``(start_days, end_days]`` of one well in history mode."""

    well: str
    kind: WellKind
    start_days: float
    end_days: float
    open: bool
    control: str                    # CMODE as written (ORAT, LRAT, RESV, RATE, BHP...)
    values: dict[str, float]        # quantity -> measured value in deck units
    source: str                     # "WCONHIST record 3 at day 0"

    @property
    def controlled(self) -> str | None:
        """The quantity this interval's control fixes (None for LRAT, RESV...)."""
        if self.kind is WellKind.PRODUCER:
            return PRODUCER_CONTROLLED.get(self.control)
        if self.control == "BHP":
            return "WBHP"
        if self.control == "RATE":
            return next((q for q in ("WWIR", "WGIR") if q in self.values), None)
        return None


@dataclass(frozen=True)
class History:
    """Every history-mode interval of a deck, and the records it could not use (with why)."""

    intervals: tuple[Interval, ...] = ()
    skipped: tuple[str, ...] = ()
    wells: frozenset[str] = field(default_factory=frozenset)

    @property
    def empty(self) -> bool:
        return not self.intervals

    def observed_table(self) -> pd.DataFrame:
        """Long table ``well, days, quantity, value, flowing, control`` of open intervals."""
        rows = [(iv.well, iv.end_days, q, v, True, iv.control)
                for iv in self.intervals if iv.open for q, v in iv.values.items()]
        return pd.DataFrame(rows, columns=["well", "days", "quantity", "value", "flowing",
                                           "control"])

    def controls(self) -> pd.DataFrame:
        """``well, start_days, end_days, controlled`` of every interval whose control fixes a
        quantity."""
        rows = [(iv.well, iv.start_days, iv.end_days, iv.controlled)
                for iv in self.intervals if iv.controlled is not None]
        return pd.DataFrame(rows, columns=["well", "start_days", "end_days", "controlled"])


def controlled_mask(observed: pd.DataFrame, history: History) -> np.ndarray:
    """Per observed row: True when its quantity is the one its well's history control fixes
    in the interval that ends on (or contains) its day."""
    ctl = history.controls()
    mask = np.zeros(len(observed), dtype=bool)
    if ctl.empty or observed.empty:
        return mask
    wells = observed["well"].to_numpy(object)
    days = observed["days"].to_numpy(float)
    qs = observed["quantity"].to_numpy(object)
    for (well, q), grp in ctl.groupby(["well", "controlled"]):
        sel = (wells == well) & (qs == q)
        if not sel.any():
            continue
        d = days[sel]
        hit = np.zeros(d.size, dtype=bool)
        for start, end in zip(grp.start_days.to_numpy(float), grp.end_days.to_numpy(float)):
            hit |= (d > start + 1e-6) & (d <= end + 1e-6)
        mask[np.flatnonzero(sel)[hit]] = True
    return mask


def read_history(deck, report_days: tuple[float, ...], wells: dict) -> History:
    """History-mode intervals from an opm.io ``Deck`` (``report_days``: days of the report
    steps from START; ``wells``: the deck's wells by name, for wildcards)."""
    names = list(wells)
    step = 0
    in_schedule = False
    active: dict[str, tuple[WellKind, bool, str, dict[str, float], str]] = {}
    counts: dict[str, int] = {}
    lists: dict[str, list[str]] = {}  # well lists (WLIST) as they stand at this point
    intervals: list[Interval] = []
    skipped: list[str] = []
    last = len(report_days) - 1

    def close_steps(n: int) -> None:
        nonlocal step
        for _ in range(n):
            if step >= last:
                return
            for well, (kind, is_open, control, values, source) in active.items():
                intervals.append(Interval(well, kind, report_days[step], report_days[step + 1],
                                          is_open, control, dict(values), source))
            step += 1

    for kw in deck:
        name = kw.name
        if name == "SCHEDULE":
            in_schedule = True
        if not in_schedule:
            continue
        if name == "TSTEP":
            for rec in kw:
                close_steps(len(rec[0].get_raw_data_list()))
        elif name == "DATES":
            close_steps(len(kw))
        elif name == "WLIST":
            for rec in kw:
                counts[name] = counts.get(name, 0) + 1
                _well_list(rec, names, lists,
                           f"{name} record {counts[name]} at day {report_days[step]:g}", skipped)
        elif name == "WELOPEN":
            for rec in kw:
                counts[name] = counts.get(name, 0) + 1
                source = f"{name} record {counts[name]} at day {report_days[step]:g}"
                items = _items(rec)
                matched = _wells(str(items.get("WELL", "")), names, source, skipped, lists)
                if any(k in items and items[k] not in (0, "") for k in
                       ("I", "J", "K", "C1", "C2")):
                    skipped.append(f"{source}: opens or shuts single connections; the well's "
                                   "history rows are kept")
                    continue
                is_open = str(items.get("STATUS", "OPEN")).upper() == "OPEN"
                for well in matched:
                    if well in active:
                        kind, _, control, values, src = active[well]
                        active[well] = (kind, is_open, control, values, src)
        elif name in ("WCONHIST", "WCONINJH", "WCONPROD", "WCONINJE"):
            for rec in kw:
                counts[name] = counts.get(name, 0) + 1
                source = f"{name} record {counts[name]} at day {report_days[step]:g}"
                items = _items(rec)
                matched = _wells(str(items.get("WELL", "")), names, source, skipped, lists)
                for well in matched:
                    if name in ("WCONPROD", "WCONINJE"):
                        active.pop(well, None)  # prediction mode: no measured rates
                        continue
                    entry = (_producer(items) if name == "WCONHIST" else _injector(items))
                    if isinstance(entry, str):
                        skipped.append(f"{source}: {entry}")
                        active.pop(well, None)
                        continue
                    kind, is_open, control, values = entry
                    active[well] = (kind, is_open, control, values, source)
    close_steps(last - step)
    return History(tuple(intervals), tuple(skipped), frozenset(i.well for i in intervals))


def _wells(pattern: str, names: list[str], source: str, skipped: list[str],
           lists: dict[str, list[str]]) -> list[str]:
    """The wells a record names: ``'*'`` is every well, ``'PROD*'`` a pattern, ``'*LIST'`` the
    wells of that list (WLIST) at this point of the schedule."""
    if pattern.startswith("*") and len(pattern) > 1:
        if pattern not in lists:
            skipped.append(f"{source}: well list '{pattern}' is not defined by a WLIST "
                           "before this record")
            return []
        return list(lists[pattern])
    matched = [w for w in names if fnmatch.fnmatchcase(w, pattern)]
    if not matched:
        skipped.append(f"{source}: well '{pattern}' is not defined in the deck")
    return matched


def _well_list(rec, names: list[str], lists: dict[str, list[str]], source: str,
               skipped: list[str]) -> None:
    """Apply one WLIST record: NEW makes the list anew, ADD appends, DEL removes, MOV moves
    the wells from every other list into this one (as OPM Flow does)."""
    item = rec[2]
    wanted = [str(item.get_str(k)) for k in range(len(item))]
    items = _items(rec)
    name, action = str(items.get("NAME", "")), str(items.get("ACTION", "")).upper()
    wells = []
    for w in wanted:
        if w.startswith("*") and len(w) > 1:  # another list, as it stands now
            if w not in lists:
                skipped.append(f"{source}: well list '{w}' in list '{name}' is not defined "
                               "by a WLIST before this record")
            wells += [n for n in lists.get(w, []) if n not in wells]
            continue
        found = [n for n in names if fnmatch.fnmatchcase(n, w)]
        if not found:
            skipped.append(f"{source}: well '{w}' of list '{name}' is not defined in the deck")
        wells += [n for n in found if n not in wells]
    if action == "NEW":
        lists[name] = wells
    elif action in ("ADD", "MOV"):
        if action == "MOV":
            for other in lists.values():
                other[:] = [w for w in other if w not in wells]
        lists.setdefault(name, [])
        lists[name] += [w for w in wells if w not in lists[name]]
    elif action == "DEL":
        if name in lists:
            lists[name] = [w for w in lists[name] if w not in wells]
    else:
        skipped.append(f"{source}: WLIST action '{action}' is not NEW, ADD, MOV or DEL")


def _items(rec) -> dict[str, object]:
    """A record's items by name; defaulted numeric items are left out."""
    out: dict[str, object] = {}
    for i in range(len(rec)):
        item = rec[i]
        try:
            if item.is_uda():
                out[item.name()] = float(item.get_uda(0).get_double())
            elif item.is_string():
                out[item.name()] = item.get_str(0)
            elif item.is_double():
                out[item.name()] = float(item.get_raw(0))
            elif item.is_int():
                out[item.name()] = int(item.get_int(0))
        except Exception:  # a defaulted item has no value
            continue
    return out


def _producer(items: dict) -> tuple | str:
    status = str(items.get("STATUS", "OPEN")).upper()
    control = str(items.get("CMODE", "")).upper()
    # a defaulted rate is 0 (as in Eclipse and OPM): a dry well's measured water, say
    values = {q: float(items.get(k, 0.0)) for q, k in (("WOPR", "ORAT"), ("WWPR", "WRAT"),
                                                       ("WGPR", "GRAT"))}
    bhp = items.get("BHP")
    if isinstance(bhp, float) and bhp > 0:
        values["WBHP"] = bhp
    return WellKind.PRODUCER, status == "OPEN", control, values


def _injector(items: dict) -> tuple | str:
    phase = str(items.get("TYPE", "")).upper()
    status = str(items.get("STATUS", "OPEN")).upper()
    quantity = INJECTED.get(phase)
    if quantity is None:
        return f"injector type '{phase}' is not matched (water and gas are)"
    values = {quantity: float(items.get("RATE", 0.0))}  # defaulted: 0, as in the simulator
    bhp = items.get("BHP")
    if isinstance(bhp, float) and bhp > 0:
        values["WBHP"] = bhp
    control = str(items.get("CMODE", "RATE")).upper()
    return WellKind.INJECTOR, status == "OPEN", control, values
