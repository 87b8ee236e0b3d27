"""What one ES-MDA update of fields costs: wall time and peak memory, no simulation.

    python benchmarks/field_update.py                 # the report's figures (see --help)
    python benchmarks/field_update.py --cells 1761 --properties 3 --members 100 \\
        --observations 300 --localisation none adaptive distance
    python benchmarks/field_update.py --prior         # PUNQ-S3's prior: 100 members drawn

Each case runs in a fresh subprocess, so that its peak resident memory (``ru_maxrss``) is its
own: the ensemble ``X`` ``(members, cells x properties)`` float32 is drawn there, the responses
``Y`` ``(members, observations)`` are made from the cells near 30 wells (each datum the mean of
20 cells of the first property near its well, plus noise: a datum is informed by few cells,
as a well's pressure is), and :func:`hmcore.fields.smoother.assimilate` runs (iteration 0 of
ERT's schedule 4, 2, 1) with the default batch size (256 MiB of working memory a batch):
once timed, once under tracemalloc. Reported: the update's wall time, the size of ``X``, the
process's peak RSS, and the peak of what the update itself allocated (tracemalloc, which numpy
reports to; the posterior array, as large as ``X``, included). Cells lie on a 5 km x 5 km square (x, y uniform); distance
localisation uses a 1,500 m radius around the wells. Run it on a quiet machine.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hmcore.fields.ensemble import EnsembleSpec  # after the path is set
from hmcore.fields.smoother import Observations, SmootherSettings, assimilate

WELLS = 30
CELLS_PER_DATUM = 20
SUITE = [  # (cells, properties, members, observations, localisation)
    (1761, 1, 100, 300, "none"), (1761, 3, 100, 300, "none"),
    (1761, 3, 100, 300, "adaptive"), (1761, 3, 100, 300, "distance"),
    (1_000_000, 3, 100, 300, "none"), (1_000_000, 3, 100, 300, "distance"),
]
"""Adaptive localisation on 3,000,000 parameters is left out: iterative_ensemble_smoother's
AdaptiveESMDA inverts once per group of parameters that share a pattern of correlated data,
and chance correlations above 3/sqrt(100) make thousands of groups per batch (one run was
stopped after 13 minutes). Ask for it with ``--cells 1000000 --localisation adaptive``."""


def one(cells: int, properties: int, members: int, observations: int,
        localisation: str) -> dict:
    """One update in this process; its figures."""
    rng = np.random.default_rng(0)
    X = rng.standard_normal((members, cells * properties), dtype=np.float32)
    xy = rng.uniform(0.0, 5000.0, (cells, 2))
    wells = rng.uniform(500.0, 4500.0, (WELLS, 2))
    datum_well = np.arange(observations) % WELLS
    Y = np.empty((members, observations))
    for o, w in enumerate(datum_well):
        near = np.argpartition(np.hypot(*(xy - wells[w]).T), CELLS_PER_DATUM)[:CELLS_PER_DATUM]
        Y[:, o] = X[:, near].mean(axis=1) * (1.0 + 0.1 * (o // WELLS)) \
            + 0.1 * rng.standard_normal(members)
    obs = Observations(Y.mean(axis=0) + 0.2, np.full(observations, 0.1), wells[datum_well])
    spec = EnsembleSpec(size=members, localisation=localisation,
                        radius=1500.0 if localisation == "distance" else None)
    settings = SmootherSettings.of(spec)
    locations = np.tile(xy, (properties, 1))
    # warm up: scipy loads its linalg module on first use (0.4 s)
    assimilate(X[:, :10], Y, obs, 0, settings, locations=locations[:10])
    start = time.perf_counter()
    update = assimilate(X, Y, obs, 0, settings, locations=locations)
    seconds = time.perf_counter() - start
    assert np.isfinite(update.ensemble).all()
    batches = update.batches
    del update
    tracemalloc.start()  # a second run for memory: tracemalloc slows Python's allocations
    assimilate(X, Y, obs, 0, settings, locations=locations)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"cells": cells, "properties": properties, "members": members,
            "observations": observations, "localisation": localisation,
            "batches": batches, "seconds": round(seconds, 3),
            "x_mb": round(X.nbytes / 2**20, 1), "update_peak_mb": round(peak / 2**20, 1),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def prior_draw() -> dict:
    """PUNQ-S3's grid (opm.io) and 100 members of three fields, the azimuth drawn per member."""
    from hmcore.fields.grid import read_grid  # here: only this figure needs opm.io and gstools
    from hmcore.fields.prior import draw_prior
    from hmcore.fields.spec import FieldSpec

    grid = read_grid(REPO.parent / "shared" / "punqs3" / "PUNQS3.DATA")
    variogram = {"model": "spherical", "ranges": [2500.0, 800.0, 5.0], "azimuth": [110.0, 170.0]}
    poro = FieldSpec.model_validate({"name": "poro", "keyword": "PORO", "prior": {
        "source": "geostatistical", "seed": 1, "variogram": variogram,
        "zones": [{"layers": [k, k], "mean": 0.2, "std": 0.04} for k in range(1, 6)]}})
    permx = FieldSpec.model_validate({"name": "permx", "keyword": "PERMX", "prior": {
        "source": "relation", "from": "poro", "intercept": 0.77, "slope": 9.02, "scatter": 0.3,
        "seed": 2}})
    permz = FieldSpec.model_validate({"name": "permz", "keyword": "PERMZ", "prior": {
        "source": "relation", "from": "permx", "intercept": -0.51, "slope": 1.0, "scatter": 0.1,
        "seed": 3}})
    start = time.perf_counter()
    draw_prior([poro, permx, permz], grid, 100)
    return {"prior": "PUNQ-S3, 3 fields, 100 members, azimuth drawn",
            "seconds": round(time.perf_counter() - start, 2),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=int)
    parser.add_argument("--properties", type=int, default=3)
    parser.add_argument("--members", type=int, default=100)
    parser.add_argument("--observations", type=int, default=300)
    parser.add_argument("--localisation", nargs="+", default=["none"],
                        choices=["none", "adaptive", "distance"])
    parser.add_argument("--prior", action="store_true", help="time PUNQ-S3's prior draw")
    parser.add_argument("--case-timeout", type=float, default=900.0,
                        help="seconds a case may take before it is stopped (default 900)")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.prior:
        print(json.dumps(prior_draw()))
        return
    if args.one:
        print(json.dumps(one(args.cells, args.properties, args.members, args.observations,
                             args.localisation[0])))
        return
    cases = SUITE if args.cells is None else [
        (args.cells, args.properties, args.members, args.observations, loc)
        for loc in args.localisation]
    print("| cells | properties | members | observations | localisation | batches | update (s) "
          "| X (MiB) | update's peak (MiB) | process peak RSS (MiB) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for cells, props, members, n_obs, loc in cases:
        try:
            out = subprocess.run([sys.executable, __file__, "--one", "--cells", str(cells),
                                  "--properties", str(props), "--members", str(members),
                                  "--observations", str(n_obs), "--localisation", loc],
                                 capture_output=True, text=True, check=True,
                                 timeout=args.case_timeout)
        except subprocess.TimeoutExpired:
            print(f"| {cells:,} | {props} | {members} | {n_obs} | {loc} | | > "
                  f"{args.case_timeout} (stopped) | | | |", flush=True)
            continue
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"| {r['cells']:,} | {r['properties']} | {r['members']} | {r['observations']} | "
              f"{r['localisation']} | {r['batches']} | {r['seconds']} | {r['x_mb']} | "
              f"{r['update_peak_mb']} | {r['peak_rss_mb']} |", flush=True)


if __name__ == "__main__":
    main()
