"""A field version of the small synthetic case: the porosity and permeability of its five layers
unknown, for ensemble runs that are cheap enough to repeat on many hidden truths.

The reservoir, wells, schedule and noise are the small synthetic case's
(:data:`hmcore.scenarios.synthetic_deck.SMALL_LAYOUT`: 10 x 10 x 5 cells of 200 m, 4
producers, 3 years), with the producers' oil targets raised by :data:`RATE_SCALE`, so that a
member with poor permeability around a well falls to the BHP floor and its cumulative oil, not
only its water and gas, depends on the fields (at the small case's own targets every member
holds its rate and the field's oil is the schedule's). The case file declares :data:`FIELDS`:
a PORO field drawn per layer with gstools and a PERMX (= PERMY) field from it by a log-linear
relation with scatter, and an ``[ensemble]`` section. Its truth for ``hmflow hide --kind
field`` is drawn from that prior (:mod:`hmcore.scenarios.field_truth`); the deck's own fields
are only the base the members' fields replace.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import tomlkit

from hmcore.scenarios.synthetic import write_synthetic_case
from hmcore.scenarios.synthetic_deck import SMALL_LAYOUT, Layout

RATE_SCALE = 2.0
"""The producers' oil targets, as a multiple of the small case's."""
FIELD_LAYOUT: Layout = replace(
    SMALL_LAYOUT, name="small-fields",
    wells=tuple(replace(w, orat_sm3_day=w.orat_sm3_day * RATE_SCALE) for w in SMALL_LAYOUT.wells))
"""The small case's reservoir with the raised targets."""

FIELDS = """
[[parameters]]
name = "poro"
kind = "field"
keyword = "PORO"
low = 0.05
high = 0.35
[parameters.prior]
source = "geostatistical"
seed = 11
variogram = { model = "spherical", ranges = [1200.0, 800.0, 2.0], azimuth = 30.0 }
zones = [{ layers = [1, 1], mean = 0.2, std = 0.03 }, { layers = [2, 2], mean = 0.22, std = 0.03 },
         { layers = [3, 3], mean = 0.19, std = 0.03 }, { layers = [4, 4], mean = 0.22, std = 0.03 },
         { layers = [5, 5], mean = 0.16, std = 0.03 }]

[[parameters]]
name = "permx"
kind = "field"
keyword = "PERMX"
copies = ["PERMY"]
low = 0.5
high = 5000.0
prior = { source = "relation", from = "poro", intercept = -0.9, slope = 12.6, scatter = 0.2, seed = 12 }
"""
"""The two field parameters (a case file's ``[[parameters]]`` tables)."""


def write_field_case(dest: Path, seed: int = 0, ensemble: dict | None = None,
                     layout: Layout = FIELD_LAYOUT) -> Path:
    """The synthetic case of ``layout`` and ``seed`` written into ``dest``
    (:func:`hmcore.scenarios.synthetic.write_synthetic_case`, one OPM run) with
    :data:`FIELDS` and an ``[ensemble]`` section of ``ensemble``'s keys (size, weights,
    localisation, ...; the defaults when empty) added to its case file; returns the case
    file."""
    case = write_synthetic_case(dest, seed, layout=layout)
    doc = tomlkit.parse(case.read_text() + FIELDS)
    section = tomlkit.table()
    for key, value in (ensemble or {}).items():
        section[key] = value
    doc["ensemble"] = section
    case.write_text(tomlkit.dumps(doc))
    return case
