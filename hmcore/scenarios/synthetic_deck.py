"""The synthetic case's reservoir and its deck: grid, structure, fluids, wells, schedule, and
the seeded prior property fields, rendered as ``SYNTH.DATA`` (METRIC units).

20 x 20 x 5 cells of 100 m x 100 m, 36 m gross, on an elongated anticline (crest 2000 m) with
a small gas cap (GOC 2008 m) over saturated oil; a Fetkovich aquifer on the steep J flanks below
the water-oil contact (WOC 2060 m). Four vertical producers on oil-rate control with a 120 bar
BHP floor; monthly report steps for 7 years, every well shut in for 14 days each year. The truth
run, the noisy history and the case files: :mod:`hmcore.scenarios.synthetic`.

That is :data:`DEFAULT_LAYOUT`, the built-in case. A :class:`Layout` sizes the same reservoir
otherwise, for tests: :data:`SMALL_LAYOUT` (10 x 10 x 5 cells of 200 m, 3 years) runs about
five times faster and keeps the gas cap, the aquifer, the shut-ins and a gas and a water
breakthrough; :data:`SHORT_LAYOUT` is the built-in grid over 3 years.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass, replace

import numpy as np

from hmcore.model.case import HELD_BACK_FRACTION

GENERATOR_VERSION = "synthetic-v1"
"""Bump when the generated case changes; it names the cache directory."""

# --- grid -------------------------------------------------------------------------------------
NX, NY, NZ = 20, 20, 5
DX_M = 100.0
"""Cell size in I and J, metres."""
LAYER_DZ_M = (6.0, 8.0, 7.0, 9.0, 6.0)
"""Layer thicknesses, metres (top to bottom)."""
CREST_DEPTH_M = 2000.0
"""Depth of the top of the anticline crest, metres."""
CREST_IJ = (9.5, 10.0)
"""Crest position in 0-based cell-centre coordinates (I, J)."""
RELIEF_I_M = 35.0
"""Depth increase over 10 cells from the crest along I (the long axis), metres."""
RELIEF_J_M = 70.0
"""Depth increase over 10 cells from the crest along J (the steep flanks), metres."""

# --- fluids and contacts ----------------------------------------------------------------------
GOC_M = 2008.0
"""Gas-oil contact depth, metres."""
WOC_M = 2060.0
"""Water-oil contact depth, metres."""
P_GOC_BAR = 210.0
"""Pressure at the gas-oil contact (= bubble point of the oil there), bar."""
RS_INIT = 100.0
"""Initial dissolved gas-oil ratio of the oil zone, sm3/sm3 (saturated at P_GOC_BAR)."""

# --- aquifer ----------------------------------------------------------------------------------
AQUIFER_VOLUME_SM3 = 1.0e9
"""Initial water volume of the Fetkovich aquifer, sm3."""
AQUIFER_CT_PER_BAR = 1.0e-4
"""Total (rock + water) compressibility of the aquifer, 1/bar."""
AQUIFER_PI = 1000.0
"""Aquifer productivity index, sm3/day/bar."""

# --- property fields --------------------------------------------------------------------------
LAYER_PERM_GEOMEAN_MD = (45.0, 120.0, 18.0, 75.0, 9.0)
"""Geometric mean of PERMX per layer, mD (layer 3 is a partial baffle)."""
LOGPERM_STD = 0.8
"""Standard deviation of ln(PERMX) around the layer mean."""
CORRELATION_CELLS = 3.0
"""Standard deviation of the Gaussian smoothing kernel, cells (I and J)."""
PORO_MEAN_REF = 0.20
"""Mean porosity of a layer whose PERMX geometric mean is 45 mD (fraction)."""
PORO_PER_LOGPERM = 0.025
"""Porosity change per unit of ln(PERMX) between layer means (fraction)."""
PORO_STD = 0.03
"""Standard deviation of porosity around the layer mean (fraction)."""
PORO_LOGPERM_CORR = 0.85
"""Correlation between porosity and ln(PERMX) within a layer."""
KV_KH_GEOMEAN = 0.1
"""Geometric mean of PERMZ / PERMX."""


@dataclass(frozen=True)
class WellSpec:
    """A vertical producer: name, 1-based (i, j), completed layers (1-based k), oil target."""

    name: str
    i: int
    j: int
    layers: tuple[int, ...]
    orat_sm3_day: float


WELLS: tuple[WellSpec, ...] = (
    WellSpec("PROD1", 6, 11, (2, 3, 4, 5), 200.0),   # crest, west: gas coning, no water
    WellSpec("PROD2", 15, 10, (2, 3, 4, 5), 200.0),  # crest, east: gas coning, no water
    WellSpec("PROD3", 9, 5, (1, 2, 3), 150.0),    # south flank: later water breakthrough
    WellSpec("PROD4", 12, 17, (1, 2, 3, 4), 140.0),  # north flank: early water breakthrough
)
BHP_LIMIT_BAR = 120.0
"""BHP floor of every producer, bar."""
WELL_DIAMETER_M = 0.2
"""Wellbore diameter (COMPDAT item 9), metres."""
BASE_SKIN = 0.0
"""Skin (COMPDAT item 11) of every connection in the base deck."""
START_DATE = _dt.date(2020, 1, 1)
N_YEARS = 7
"""Length of the schedule, years (report steps on the 1st of every month)."""
SHUTIN_MONTH = 7
"""Every year all wells are shut in on the 1st of this month ..."""
SHUTIN_DAYS = 14
"""... for this many days (oil target set to 0 with WELTARG, so the BHP builds up)."""
HISTORY_FRACTION = 1.0 - HELD_BACK_FRACTION
"""Default ``history_end_days``: the report step nearest this fraction of the schedule."""


@dataclass(frozen=True)
class Layout:
    """The size of the synthetic reservoir: ``nx`` x ``ny`` cells of ``dx_m`` metres, a schedule
    of ``n_years`` and the ``wells``.

    Whatever the layout, the reservoir is the same 2 km x 2 km anticline with the same layers,
    contacts, fluids and aquifer. Lengths in cells are the default's metres over ``dx_m``:
    ``crest_ij`` (0-based cell-centre I, J), ``relief_cells`` (over which the depth grows by
    ``RELIEF_I_M`` and ``RELIEF_J_M``), and the smoothing of ln(PERMX) (``correlation_cells``),
    of porosity's own part (``poro_cells``) and of PERMZ/PERMX (``kvkh_cells``); the wells sit in
    the cells holding the default wells' positions.
    """

    name: str
    nx: int
    ny: int
    dx_m: float
    crest_ij: tuple[float, float]
    relief_cells: float
    correlation_cells: float
    poro_cells: float
    kvkh_cells: float
    n_years: int
    wells: tuple[WellSpec, ...]


DEFAULT_LAYOUT = Layout("default", NX, NY, DX_M, CREST_IJ, 10.0, CORRELATION_CELLS, 1.5, 2.0,
                        N_YEARS, WELLS)
"""The built-in synthetic case: 20 x 20 x 5 cells of 100 m, 7 years."""
SMALL_LAYOUT = Layout(
    "small", 10, 10, 200.0, (4.5, 4.75), 5.0, 1.5, 0.75, 1.0, 3,
    (WellSpec("PROD1", 3, 6, (2, 3, 4, 5), 200.0),   # crest, west: gas coning
     WellSpec("PROD2", 8, 5, (2, 3, 4, 5), 200.0),   # crest, east: gas coning
     WellSpec("PROD3", 5, 3, (1, 2, 3), 150.0),      # south flank
     WellSpec("PROD4", 6, 9, (1, 2, 3, 4), 140.0)))  # north flank: water from the start
"""10 x 10 x 5 cells of 200 m, 3 years (a shut-in after the default history end): about a
fifth of the default's simulation time, for tests of logic."""
SHORT_LAYOUT = replace(DEFAULT_LAYOUT, name="short", n_years=3)
"""The built-in grid and wells over 3 years: the default's reservoir and early history (what a
diagnosis of it sees there) at about half its simulation time."""

# ==============================================================================================
# property fields
# ==============================================================================================
@dataclass(frozen=True)
class SyntheticFields:
    """Grid geometry and prior property fields, arrays of shape (NZ, NY, NX), i.e. (k, j, i).

    ``tops`` in metres, ``poro`` as a fraction, ``permx`` and ``permz`` in mD.
    """

    tops: np.ndarray
    poro: np.ndarray
    permx: np.ndarray
    permz: np.ndarray


def _gaussian_random_field(rng: np.random.Generator, sigma_cells: float,
                           layout: Layout) -> np.ndarray:
    """White noise on one layer (ny, nx) smoothed with a Gaussian kernel of ``sigma_cells``
    cells (mirrored edges), rescaled to zero mean and unit variance."""
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(rng.standard_normal((layout.ny, layout.nx)), sigma_cells, mode="reflect")
    return (g - g.mean()) / g.std()


def _condition_to_wells(z: np.ndarray, sigma_cells: float, layout: Layout) -> np.ndarray:
    """Condition a unit Gaussian field to 0 (the layer mean) in the well columns.

    Simple kriging update ``z + sum_w lambda_w(x) * (0 - z(w))`` with the covariance of
    Gaussian-smoothed white noise, ``exp(-d^2 / (4 sigma^2))`` (d in cells): the wells see the
    layer-mean rock for every seed while the field between them keeps its variability.
    """
    jj, ii = np.meshgrid(np.arange(layout.ny, dtype=float), np.arange(layout.nx, dtype=float),
                         indexing="ij")
    pts = np.array([(w.j - 1.0, w.i - 1.0) for w in layout.wells])

    def cov(dj: np.ndarray, di: np.ndarray) -> np.ndarray:
        return np.exp(-(dj ** 2 + di ** 2) / (4.0 * sigma_cells ** 2))

    k = cov(pts[:, None, 0] - pts[None, :, 0], pts[:, None, 1] - pts[None, :, 1])
    c = np.stack([cov(jj - pj, ii - pi) for pj, pi in pts])  # (wells, ny, nx)
    lam = np.linalg.solve(k, c.reshape(len(pts), -1)).reshape(c.shape)
    at_wells = z[pts[:, 0].astype(int), pts[:, 1].astype(int)]
    return z - np.tensordot(at_wells, lam, axes=1)


def structure_tops(layout: Layout = DEFAULT_LAYOUT) -> np.ndarray:
    """Depth of the top of every cell, shape (NZ, ny, nx), metres: an elongated anticline."""
    jj, ii = np.meshgrid(np.arange(layout.ny, dtype=float), np.arange(layout.nx, dtype=float),
                         indexing="ij")
    ci, cj = layout.crest_ij
    top = (CREST_DEPTH_M + RELIEF_I_M * ((ii - ci) / layout.relief_cells) ** 2
           + RELIEF_J_M * ((jj - cj) / layout.relief_cells) ** 2)
    offsets = np.concatenate([[0.0], np.cumsum(LAYER_DZ_M)[:-1]])
    return np.stack([top + off for off in offsets])


def make_fields(rng: np.random.Generator, layout: Layout = DEFAULT_LAYOUT) -> SyntheticFields:
    """Prior fields drawn from ``rng``: layered log-normal PERMX, porosity tied to ln(PERMX).

    Per layer k: ``ln PERMX = ln(mean_k) + LOGPERM_STD * z`` with ``z`` a unit Gaussian random
    field (white noise smoothed over ``layout.correlation_cells``) conditioned to 0 at the wells
    (the wells are "logged" at the layer mean, so every seed gives workable wells); porosity has
    layer mean ``PORO_MEAN_REF + PORO_PER_LOGPERM * ln(mean_k / 45 mD)`` and correlation
    ``PORO_LOGPERM_CORR`` with ``z``; PERMZ/PERMX is log-normal around ``KV_KH_GEOMEAN``.
    """
    shape = (NZ, layout.ny, layout.nx)
    logk = np.empty(shape)
    poro = np.empty(shape)
    kvkh = np.empty(shape)
    c = PORO_LOGPERM_CORR
    for k in range(NZ):
        z = _condition_to_wells(_gaussian_random_field(rng, layout.correlation_cells, layout),
                                layout.correlation_cells, layout)
        zp = c * z + np.sqrt(1.0 - c * c) * _gaussian_random_field(rng, layout.poro_cells,
                                                                   layout)
        logk[k] = np.log(LAYER_PERM_GEOMEAN_MD[k]) + LOGPERM_STD * z
        poro[k] = (PORO_MEAN_REF + PORO_PER_LOGPERM * np.log(LAYER_PERM_GEOMEAN_MD[k] / 45.0)
                   + PORO_STD * zp)
        kvkh[k] = KV_KH_GEOMEAN * np.exp(0.3 * _gaussian_random_field(rng, layout.kvkh_cells,
                                                                      layout))
    permx = np.exp(logk)
    return SyntheticFields(tops=structure_tops(layout), poro=np.clip(poro, 0.05, 0.35), permx=permx,
                           permz=permx * kvkh)


# ==============================================================================================
# schedule
# ==============================================================================================
@dataclass(frozen=True)
class ReportStep:
    """One report step: the date it ends, days since START, and the wells producing in it."""

    date: _dt.date
    days: float
    open_wells: frozenset[str]


def _first_of_month(d: _dt.date, months_later: int) -> _dt.date:
    m = d.month - 1 + months_later
    return _dt.date(d.year + m // 12, m % 12 + 1, 1)


def report_steps(layout: Layout = DEFAULT_LAYOUT) -> list[ReportStep]:
    """Report steps: the 1st of every month, plus the end of each yearly shut-in.

    All wells are shut from the 1st of ``SHUTIN_MONTH`` for ``SHUTIN_DAYS`` days every year, so
    the step ending then has no producing well and its BHP is the built-up pressure.
    """
    all_wells = frozenset(w.name for w in layout.wells)
    steps: list[ReportStep] = []
    for m in range(12 * layout.n_years):
        month_start = _first_of_month(START_DATE, m)
        if month_start.month == SHUTIN_MONTH:
            shut_end = month_start + _dt.timedelta(days=SHUTIN_DAYS)
            steps.append(ReportStep(shut_end, float((shut_end - START_DATE).days), frozenset()))
        end = _first_of_month(START_DATE, m + 1)
        steps.append(ReportStep(end, float((end - START_DATE).days), all_wells))
    return steps


def default_history_end_days(layout: Layout = DEFAULT_LAYOUT) -> float:
    """The report day nearest ``HISTORY_FRACTION`` of the schedule, days since START."""
    days = np.array([s.days for s in report_steps(layout)])
    return float(days[np.argmin(np.abs(days - HISTORY_FRACTION * days[-1]))])


# ==============================================================================================
# deck
# ==============================================================================================
_MONTHS = ("JAN", "FEB", "MAR", "APR", "MAY", "JUN", "JUL", "AUG", "SEP", "OCT", "NOV", "DEC")


def _eclipse_date(d: _dt.date) -> str:
    return f"{d.day} '{_MONTHS[d.month - 1]}' {d.year}"


def _format_array(values: np.ndarray, fmt: str, per_line: int = 8) -> str:
    flat = np.asarray(values, dtype=float).ravel()  # C order of (k, j, i) = Eclipse order
    lines = [" " + " ".join(fmt.format(v) for v in flat[s:s + per_line])
             for s in range(0, flat.size, per_line)]
    return "\n".join(lines) + "\n/\n"


def _swof() -> str:
    """Water-oil relative permeability (Corey, Swc 0.2, Sorw 0.2) and capillary pressure."""
    swc, sorw = 0.20, 0.20
    rows = []
    for sw in np.linspace(swc, 1.0, 17):
        swn = min(max((sw - swc) / (1.0 - swc - sorw), 0.0), 1.0)
        krw = 0.4 * swn ** 2.5 if sw <= 1.0 - sorw + 1e-12 else \
            0.4 + 0.6 * (sw - 1.0 + sorw) / sorw
        krow = (1.0 - swn) ** 2.0
        pc = 0.3 * (1.0 - swn) ** 3.0
        rows.append(f" {sw:.4f} {krw:.6f} {krow:.6f} {pc:.4f}")
    return "SWOF\n-- Sw krw krow Pcow(bar)\n" + "\n".join(rows) + "\n/\n"


def _sgof() -> str:
    """Gas-oil relative permeability (Corey, Sgc 0.05, Sorg 0.1), no capillary pressure."""
    swc, sgc, sorg = 0.20, 0.05, 0.10
    sgmax = 1.0 - swc
    rows = []
    for sg in np.concatenate([[0.0], np.linspace(sgc, sgmax, 16)]):
        krg = 0.8 * ((sg - sgc) / (sgmax - sgc)) ** 2.0 if sg > sgc else 0.0
        krog = max((1.0 - swc - sorg - sg) / (1.0 - swc - sorg), 0.0) ** 2.5
        rows.append(f" {sg:.4f} {krg:.6f} {krog:.6f} 0.0")
    return "SGOF\n-- Sg krg krog Pcog(bar)\n" + "\n".join(rows) + "\n/\n"


_PVT = f"""PVTO
-- Rs(sm3/sm3) P(bar) Bo(rm3/sm3) mu_o(cP)
   10.0    30.0   1.060  1.60
           200.0  1.045  1.85 /
   30.0    70.0   1.110  1.30
           250.0  1.090  1.50 /
   50.0   110.0   1.160  1.10
           300.0  1.136  1.27 /
   70.0   150.0   1.210  0.95
           300.0  1.188  1.08 /
   90.0   190.0   1.260  0.83
           350.0  1.234  0.96 /
  110.0   230.0   1.310  0.74
           400.0  1.280  0.86 /
  130.0   270.0   1.360  0.66
           450.0  1.326  0.77 /
/

PVDG
-- P(bar) Bg(rm3/sm3) mu_g(cP)
    20.0   0.05700   0.0130
    50.0   0.02250   0.0136
   100.0   0.01120   0.0146
   150.0   0.00760   0.0160
   200.0   0.00580   0.0176
   250.0   0.00478   0.0192
   300.0   0.00412   0.0208
   400.0   0.00330   0.0238
   500.0   0.00285   0.0266
/

PVTW
-- Pref(bar) Bw(rm3/sm3) cw(1/bar) mu_w(cP) viscosibility(1/bar)
 {P_GOC_BAR:.1f} 1.020 4.5E-05 0.40 0.0 /

ROCK
-- Pref(bar) cr(1/bar)
 {P_GOC_BAR:.1f} 5.0E-05 /

DENSITY
-- oil water gas (kg/m3)
 850.0 1030.0 0.90 /
"""


def _schedule_section(layout: Layout) -> str:
    out = ["SCHEDULE", "", "RPTONLY", "", "WELSPECS",
           "-- well group I J BHP-depth phase"]
    out += [f" '{w.name}' 'G1' {w.i} {w.j} 1* 'OIL' /" for w in layout.wells]
    out += ["/", "", "COMPDAT",
            "-- well I J K1 K2 status satnum CF diam(m) Kh skin Dfac dir"]
    for w in layout.wells:
        for k in w.layers:
            out.append(f" '{w.name}' {w.i} {w.j} {k} {k} 'OPEN' 1* 1* {WELL_DIAMETER_M:.2f} 1* "
                       f"{BASE_SKIN:.1f} 1* 'Z' /")
    out += ["/", "", "WCONPROD", "-- well status control ORAT WRAT GRAT LRAT RESV BHP"]
    out += [f" '{w.name}' 'OPEN' 'ORAT' {w.orat_sm3_day:.1f} 4* {BHP_LIMIT_BAR:.1f} /"
            for w in layout.wells]
    out += ["/", ""]
    is_open = frozenset(w.name for w in layout.wells)
    for step in report_steps(layout):
        if step.open_wells != is_open:  # controls for a step precede the DATES that ends it
            out.append("WELTARG")
            out += [f" '{w.name}' 'ORAT' "
                    f"{w.orat_sm3_day if w.name in step.open_wells else 0.0:.1f} /"
                    for w in layout.wells]
            out += ["/", ""]
            is_open = step.open_wells
        out += ["DATES", f" {_eclipse_date(step.date)} /", "/", ""]
    out += ["END", ""]
    return "\n".join(out)


def render_deck(fields: SyntheticFields, seed: int, layout: Layout = DEFAULT_LAYOUT) -> str:
    """The base deck text: prior ``fields`` and base skin ``BASE_SKIN`` on every connection.

    Section and data keywords start at column 0 on their own line; every COMPDAT connection is
    one record on one line (quoted well name, K1 = K2, skin in item 11) and the list ends with a
    lone ``/``; COMPDAT item 8 (connection factor) is defaulted so OPM computes it from Kh, the
    diameter and the skin (a given factor would make the skin ineffective). Arrays are written
    inline (no INCLUDE files); the GRID section ends with ``COPY PERMX PERMY`` and AQUANCON, so
    a MULTIPLY block inserted before PROPS scales PERMX and PERMY independently.
    """
    nx, ny, wells_ = layout.nx, layout.ny, layout.wells
    n = nx * ny * NZ
    wells = " ".join(f"'{w.name}'" for w in wells_)
    dz = " ".join(f"{nx * ny}*{dz:.2f}" for dz in LAYER_DZ_M)
    size = "" if layout == DEFAULT_LAYOUT else \
        f" ({layout.name} layout: {nx} x {ny} x {NZ} cells, {layout.n_years} years)"
    summary = ["SUMMARY", ""]
    for kw in ("FOPT", "FWPT", "FGPT", "FPR", "FOPR", "FWPR", "FGPR"):
        summary += [kw, ""]
    for kw in ("WBHP", "WOPR", "WWPR", "WGPR", "WGOR", "WWCT"):
        summary += [kw, f" {wells} /", ""]
    return (
        f"""-- hmflow synthetic case {GENERATOR_VERSION}, seed {seed}{size}: written by hmcore.scenarios.synthetic
-- 3-phase black oil (METRIC), anticline with a gas cap, Fetkovich aquifer on the flanks,
-- {len(wells_)} oil-rate-controlled producers, monthly report steps, yearly 2-week shut-ins.

RUNSPEC

TITLE
hmflow synthetic case seed {seed}

DIMENS
 {nx} {ny} {NZ} /

OIL

WATER

GAS

DISGAS

METRIC

START
 {_eclipse_date(START_DATE)} /

EQLDIMS
 1 /

TABDIMS
-- NTSFUN NTPVT NSSFUN NPPVT
 1 1 20 20 /

WELLDIMS
-- wells connections/well groups wells/group
 {len(wells_)} {NZ} 1 {len(wells_)} /

AQUDIMS
-- 4* analytic-aquifers connections/aquifer
 4* 1 {2 * nx * NZ} /

UNIFOUT

GRID

DX
 {n}*{layout.dx_m:.1f} /

DY
 {n}*{layout.dx_m:.1f} /

DZ
 {dz} /

TOPS
{_format_array(fields.tops, "{:.3f}")}
PORO
{_format_array(fields.poro, "{:.5f}")}
PERMX
{_format_array(fields.permx, "{:.4f}")}
PERMZ
{_format_array(fields.permz, "{:.5f}")}
COPY
 PERMX PERMY /
/

AQUANCON
-- aquifer I1 I2 J1 J2 K1 K2 face
 1 1 {nx} 1 1 1 {NZ} 'J-' /
 1 1 {nx} {ny} {ny} 1 {NZ} 'J+' /
/

PROPS

{_swof()}
{_sgof()}
{_PVT}
REGIONS

SOLUTION

EQUIL
-- datum(m) P(bar) WOC(m) Pcow GOC(m) Pcog Rs-table
 {GOC_M:.1f} {P_GOC_BAR:.1f} {WOC_M:.1f} 0.0 {GOC_M:.1f} 0.0 1 0 0 /

RSVD
-- depth(m) Rs(sm3/sm3)
 1900.0 {RS_INIT:.1f}
 2200.0 {RS_INIT:.1f} /

AQUFETP
-- id datum(m) P0 volume(sm3) ct(1/bar) PI(sm3/day/bar) PVTW-table
 1 {WOC_M:.1f} 1* {AQUIFER_VOLUME_SM3:.4E} {AQUIFER_CT_PER_BAR:.2E} {AQUIFER_PI:.1f} 1 /
/

""" + "\n".join(summary) + "\n" + _schedule_section(layout))
