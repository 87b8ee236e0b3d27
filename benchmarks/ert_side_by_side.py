"""ERT and hmflow side by side on one field case (issue 42, first bullet): the same prior
realisations, observations, noise, ensemble size and inflation weights, the same OPM Flow, 2
runs at a time; judged from each tool's own outputs by the same formulas.

    .venv/bin/python benchmarks/ert_side_by_side.py --case /work/bench/calib/truth-1/case.toml \
        --out /work/bench/ert/synthetic-truth-1 --ert /work/ert26-venv/bin/ert \
        [--stage all|prepare|ert|hmflow|compare] [--results benchmarks/results/ert]

ERT is never a dependency of hmflow: it lives in its own virtual environment (``--ert``, its
``ert`` command), used by this script only through that command.

1. prepare (``OUT/``): hmflow's prior of the case (``draw_ensemble``, its seeds: the members
   ``hmflow ensemble`` would draw) written as one GRDECL file per member and field
   (``prior/poro_<m>.grdecl`` with PORO, ``prior/permx_<m>.grdecl`` with PERMX: physical
   values, truncated to the field's bounds, as hmflow writes a member); then

   * ``hmflow-case/case.toml``: the case with each field's prior ``source = "files"`` on those
     files (the same members for both tools) and the truth's ``hidden_truth.json`` beside it;
   * ``ert/``: ERT's configuration ``synth.ert``: ``FIELD`` per field with ``INIT_FILES`` on
     the same files (``FORWARD_INIT:False``; permeability updated in log10 like hmflow, by
     ``INIT_TRANSFORM:LOG10``/``OUTPUT_TRANSFORM:POW10``; ``MIN``/``MAX`` the case's bounds),
     ``GRID`` the deck's EGRID (from one run of the deck), the deck as ``DATA_FILE`` with the
     fields' files as ``INCLUDE`` at the end of GRID (and ``COPY PERMX PERMY`` after them, the
     case's ``copies``), ``OBS_CONFIG``: every datum hmflow fits (``ObservationSet.from_case``:
     the rows of its whitened vector) as a ``SUMMARY_OBSERVATION`` with hmflow's sigma of
     that row as ``ERROR``, ``NUM_REALIZATIONS`` the ensemble's size, ``MIN_REALIZATIONS``
     hmflow's minimum (half), ``QUEUE_SYSTEM LOCAL`` with ``MAX_RUNNING 2``, ``NUM_CPU 1``
     and a forward model ``OPM_FLOW`` (``INSTALL_JOB``) that runs the deck with OPM Flow
     exactly as hmflow does (``python -m hmcore.simulation.opm_runner`` of hmflow's
     environment: the ``opm-simulators`` bindings, one fresh process per run).

   What ERT cannot be told: hmflow whitens the residuals of a well's series with an AR(1)
   correlation (rho per quantity, ``hmflow check`` prints it); ERT's observation errors are
   independent, so ERT gets the same sigma without the correlation.
2. ert: ``ert es_mda --weights 4,2,1 synth.ert`` in ``OUT/ert`` (the case's weights), timed;
   skipped when ``OUT/ert/run.json`` records a finished run.
3. hmflow: ``hmflow ensemble --case OUT/hmflow-case/case.toml --storage OUT/hmflow-store
   --campaign files-es --workers 2``, timed; skipped when ``OUT/hmflow.json`` records a
   finished run (and hmflow itself resumes a broken one without simulating a member twice).
4. compare, from the runs' own files: every run's summary (ERT's run paths
   ``simulations/realization-<m>/iter-<i>``; hmflow's journaled run directories) read by the
   same code, so the formulas are the same for both:

   * data misfit of a run: the mean square of its standardized residuals
     ``(simulated - observed) / sigma`` over the fitted rows (``misfit_diag``, what ERT
     minimises) and of hmflow's AR(1)-whitened ones (``misfit_ar1``, what hmflow minimises
     and reports); median and mean over the prior's and the posterior's runs;
   * the forecast at the schedule's end (``forecast_table``: P90 the low case, 10th
     percentile; P10 the high case) of FOPT and each well's WOPT, prior and posterior, and
     whether the truth's value lies inside P90-P10 (and its percentile among the members);
   * RMSE of the posterior mean field to the truth (``truth.GRDECL``) in update space (PORO
     as it is, log10 PERMX) from the field files each tool wrote for its last runs (ERT's
     ``poro.grdecl``/``permx.grdecl`` in the ``iter-3`` run paths, hmflow's
     ``FIELDS.GRDECL``), and the members' mean standard deviation (spread);
   * wall time of the command, simulations, failed realisations, and what each tool printed.

   Written to ``--results`` (``<name>.json``, ``<name>-table.csv``, ``<name>-members.csv``)
   and printed as Markdown.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import tomlkit

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hmcore.cases import load_case
from hmcore.fields.assimilation import draw_ensemble
from hmcore.fields.grdecl import INACTIVE_VALUE, read_grdecl, write_grdecl
from hmcore.fields.grid import read_grid
from hmcore.fields.transform import to_physical, to_update_space
from hmcore.scoring.observations import ObservationSet
from hmcore.simulation.curves import read_curves
from hmcore.simulation.forecast import forecast_table
from hmcore.simulation.responses import read_responses

PYTHON = Path(sys.executable)
HMFLOW = PYTHON.parent / "hmflow"
CAMPAIGN = "files-es"
VARIANTS = {"hmflow": ("hmflow-case", CAMPAIGN),
            "hmflow-white": ("hmflow-case-white", f"{CAMPAIGN}-white")}
"""hmflow's runs: as it is, and told ERT's noise model (the same sigma, no time correlation):
{tool: (case folder in OUT, campaign in OUT/hmflow-store)}."""
ECLBASE = "SYNTH"
CONFIG = "synth.ert"
WORKERS = 2


# ============================================================================ prepare
def prepare(case_path: Path, out: Path, seed: int = 0) -> dict:
    """Write the prior files, hmflow's files-prior case and ERT's configuration (module doc,
    step 1); returns what was written. Idempotent: the prior is drawn from the case's seeds."""
    case = load_case(case_path)
    grid = read_grid(case.deck)
    size = case.ensemble.size
    prior = draw_ensemble(case.fields, grid, size, case.space.names, case.ensemble.seed)
    fields = prior.layout.split(prior.X)[0]
    folder = out / "prior"
    folder.mkdir(parents=True, exist_ok=True)
    for f in case.fields:
        for m in range(size):
            write_grdecl(folder / f"{f.name}_{m}.grdecl",
                         {f.keyword: grid.full(to_physical(fields[f.name][m], f),
                                               fill=INACTIVE_VALUE)},
                         header=f"{case.name}: member {m} of hmflow's prior of field "
                                f"{f.name} (seed {prior.seeds.get(f.name)})")
    hm_case = write_hmflow_case(case_path, out / VARIANTS["hmflow"][0], seed=seed)
    write_hmflow_case(case_path, out / VARIANTS["hmflow-white"][0], white=True, seed=seed)
    ert_dir = write_ert_config(case, grid, out / "ert", folder, seed)
    return {"prior": str(folder), "hmflow_case": str(hm_case), "ert_config": str(ert_dir / CONFIG),
            "members": size, "seeds": dict(prior.seeds)}


def write_hmflow_case(case_path: Path, dest: Path, white: bool = False, seed: int = 0) -> Path:
    """A copy of the case file with every field's prior replaced by ``source = "files"`` on
    ``../prior/<field>_*.grdecl``; the deck and observed file absolute; the truth's
    ``hidden_truth.json`` beside it when the case has one (so the report draws the truth).

    ``white``: the case told ERT's noise model, as an ablation: the observed table with a
    ``sigma`` column (hmflow's own sigma of each fitted row, which it then keeps as given) and
    ``[noise.Q] correlation_days = 0`` for every quantity (no AR(1) whitening). ``seed``:
    the ensemble's seed (of the observation perturbations) when not 0."""
    dest.mkdir(parents=True, exist_ok=True)
    doc = tomlkit.parse(case_path.read_text())
    base = case_path.parent
    for key in ("deck", "observed"):
        doc["case"][key] = str((base / str(doc["case"][key])).resolve())
    doc["case"]["name"] = f"{doc['case']['name']}-files" + ("-white" if white else "")
    if seed:
        doc["ensemble"]["seed"] = seed
    if white:
        obs = ObservationSet.from_case(load_case(case_path))
        rows = obs.rows.iloc[obs.vector_index("fit")][["well", "quantity", "days", "sigma"]]
        observed = pd.read_csv(doc["case"]["observed"])
        merged = observed.merge(rows, on=["well", "quantity", "days"], how="left")
        if len(merged) != len(observed):
            raise SystemExit("the observed table has repeated (well, quantity, days) rows")
        merged.to_csv(dest / "observed.csv", index=False)
        doc["case"]["observed"] = "observed.csv"
        noise = tomlkit.table(is_super_table=True)
        for q in sorted(obs.rows.quantity.unique()):
            level = tomlkit.table()
            level["correlation_days"] = 0.0
            noise[q] = level
        doc["noise"] = noise
    for p in doc["parameters"]:
        if p.get("kind") == "field":
            prior = tomlkit.inline_table()
            prior.update({"source": "files", "folder": "../prior",
                          "pattern": f"{p['name']}_*.grdecl"})
            p["prior"] = prior
    target = dest / "case.toml"
    target.write_text(tomlkit.dumps(doc))
    truth = base / "hidden_truth.json"
    if truth.is_file():
        shutil.copyfile(truth, dest / "hidden_truth.json")
    return target


def ert_deck(text: str, includes: list[str], copies: list[tuple[str, str]]) -> str:
    """The deck with ERT's field files included at the end of GRID (before PROPS or EDIT) and
    the case's copies after them."""
    lines = ["-- ERT's FIELD parameters, written by ERT into each run path\n"]
    lines += [f"INCLUDE\n  '{name}' /\n\n" for name in includes]
    if copies:
        lines.append("COPY\n" + "".join(f"  {a} {b} /\n" for a, b in copies) + "/\n\n")
    block = "".join(lines)
    match = re.search(r"^(EDIT|PROPS)\s*$", text, flags=re.MULTILINE)
    if match is None:
        raise SystemExit("the deck has no EDIT or PROPS section after GRID in its main file")
    return text[:match.start()] + block + text[match.start():]


def write_ert_config(case, grid, ert_dir: Path, prior: Path, seed: int = 0) -> Path:
    """ERT's configuration in ``ert_dir`` (module doc, step 1); ``seed``: ERT's RANDOM_SEED
    (123456789, the first run's, for 0)."""
    ert_dir.mkdir(parents=True, exist_ok=True)
    # the grid ERT maps FIELD values on: the deck's own EGRID, from one run of the deck
    base_run = ert_dir / "base-run"
    if not (base_run / f"{ECLBASE}.EGRID").is_file():
        base_run.mkdir(exist_ok=True)
        shutil.copyfile(case.deck, base_run / f"{ECLBASE}.DATA")
        subprocess.run([str(PYTHON), "-m", "hmcore.simulation.opm_runner", f"{ECLBASE}.DATA",
                        str(base_run)], cwd=base_run, check=True,
                       stdout=subprocess.DEVNULL)
    shutil.copyfile(base_run / f"{ECLBASE}.EGRID", ert_dir / f"{ECLBASE}.EGRID")

    field_lines, includes, copies = [], [], []
    for f in case.fields:
        low, high = f.bounds
        out_file = f"{f.name}.grdecl"
        includes.append(out_file)
        copies += [(f.keyword, c) for c in f.copies]
        transform = " INIT_TRANSFORM:LOG10 OUTPUT_TRANSFORM:POW10" if f.in_log else ""
        init = os.path.relpath(prior / f"{f.name}_<IENS>.grdecl", ert_dir)
        field_lines.append(f"FIELD {f.keyword} PARAMETER {out_file} INIT_FILES:{init} "
                           f"FORWARD_INIT:False{transform} MIN:{low:g} MAX:{high:g}")
    (ert_dir / f"{ECLBASE}.DATA").write_text(
        ert_deck(Path(case.deck).read_text(errors="replace"), includes, copies))

    obs = ObservationSet.from_case(case)
    start = case.info.start
    rows = obs.rows.iloc[obs.vector_index("fit")]
    blocks = []
    for r in rows.itertuples():
        date = start + dt.timedelta(days=float(r.days))
        name = f"{r.quantity}_{r.well}_{round(r.days)}"
        blocks.append(f"SUMMARY_OBSERVATION {name}\n{{\n   VALUE = {r.observed!r};\n"
                      f"   ERROR = {float(r.sigma)!r};\n   DATE  = {date:%Y-%m-%d};\n"
                      f"   KEY   = {r.quantity}:{r.well};\n}};\n")
    (ert_dir / "observations.txt").write_text(
        f"-- hmflow's fitted data of {case.name}: {len(rows)} rows, ERROR = hmflow's sigma of "
        "the row (ObservationSet.from_case); hmflow's AR(1) time correlation is not "
        "expressible here\n" + "".join(blocks))

    runner = ert_dir / "opm_flow.sh"
    runner.write_text("#!/bin/sh\n# OPM Flow as hmflow runs it: the opm-simulators bindings of "
                      "hmflow's environment, one process per run\n"
                      f"exec {PYTHON} -m hmcore.simulation.opm_runner \"$1\" \"$PWD\"\n")
    runner.chmod(0o755)
    (ert_dir / "OPM_FLOW").write_text("EXECUTABLE opm_flow.sh\nARGLIST <DECK>\n"
                                      "STDOUT opm_flow.stdout\nSTDERR opm_flow.stderr\n")
    spec = case.ensemble
    config = [
        f"-- written by benchmarks/ert_side_by_side.py from {case.source}",
        f"NUM_REALIZATIONS {spec.size}",
        f"MIN_REALIZATIONS {spec.minimum}",
        "QUEUE_SYSTEM LOCAL",
        f"MAX_RUNNING {WORKERS}",
        "NUM_CPU 1",
        f"RANDOM_SEED {seed or 123456789}",
        "RUNPATH simulations/realization-<IENS>/iter-<ITER>",
        "ENSPATH storage",
        f"ECLBASE {ECLBASE}",
        f"DATA_FILE {ECLBASE}.DATA",
        f"GRID {ECLBASE}.EGRID",
        "OBS_CONFIG observations.txt",
        "SUMMARY FOPT FWPT FGPT",
        "SUMMARY WOPR:* WWPR:* WGPR:* WBHP:* WGOR:* WWCT:* WOPT:*",
        *field_lines,
        "INSTALL_JOB OPM_FLOW OPM_FLOW",
        f"FORWARD_MODEL OPM_FLOW(<DECK>={ECLBASE}.DATA)",
    ]
    (ert_dir / CONFIG).write_text("\n".join(config) + "\n")
    return ert_dir


# ============================================================================ runs
def timed(cmd: list[str], cwd: Path, log: Path, record: Path, env: dict | None = None) -> dict:
    """Run ``cmd`` (stdout and stderr to ``log``), timed; the record written to ``record``.
    Kept when ``record`` says it finished (exit 0): a finished run is not done again."""
    if record.is_file():
        doc = json.loads(record.read_text())
        if doc.get("returncode") == 0:
            print(f"kept: {' '.join(cmd)} finished before ({doc['wall_s']:.0f} s)")
            return doc
    started = time.time()
    load = os.getloadavg()
    with open(log, "w") as fh:
        proc = subprocess.run(cmd, cwd=cwd, stdout=fh, stderr=subprocess.STDOUT, check=False,
                              env={**os.environ, **(env or {})})
    doc = {"command": cmd, "cwd": str(cwd), "returncode": proc.returncode,
           "wall_s": time.time() - started, "started": dt.datetime.fromtimestamp(
               started, dt.UTC).isoformat(timespec="seconds"),
           "load_at_start": load, "load_at_end": os.getloadavg(), "log": str(log)}
    record.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"{' '.join(cmd)}: exit {proc.returncode} after {doc['wall_s']:.0f} s (log {log})")
    return doc


def run_ert(ert: Path, out: Path, weights: tuple[float, ...]) -> dict:
    w = ",".join(f"{x:g}" for x in weights)
    # ERT's local queue starts its job dispatcher (fm_dispatch.py) from PATH: its venv's bin
    path = f"{ert.parent}{os.pathsep}{os.environ.get('PATH', '')}"
    return timed([str(ert), "es_mda", "--weights", w, CONFIG], out / "ert",
                 out / "ert" / "ert.log", out / "ert" / "run.json", env={"PATH": path})


def run_hmflow(out: Path, tool: str = "hmflow") -> dict:
    folder, campaign = VARIANTS[tool]
    return timed([str(HMFLOW), "ensemble", "--case", str(out / folder / "case.toml"),
                  "--storage", str(out / "hmflow-store"), "--campaign", campaign,
                  "--workers", str(WORKERS)], out, out / f"{tool}.log", out / f"{tool}.json")


# ============================================================================ compare
def ert_runs(out: Path, rounds: int, size: int) -> list[dict]:
    """Every (iteration, member) ERT was to run: its run path, summary and status (ERT's job
    dispatch leaves ``OK`` in a run path whose forward model succeeded)."""
    rows = []
    for i in range(rounds):
        for m in range(size):
            path = out / "ert" / "simulations" / f"realization-{m}" / f"iter-{i}"
            smspec = path / f"{ECLBASE}.SMSPEC"
            ok = (path / "OK").is_file() and smspec.is_file()
            status = path / "status.json"  # ERT's job dispatch: start and end, whole seconds
            times = json.loads(status.read_text()) if status.is_file() else {}
            rows.append({"tool": "ert", "iteration": i, "member": m, "run_dir": str(path),
                         "ran": path.is_dir(), "ok": ok,
                         "summary": str(smspec) if ok else None,
                         "start": times.get("start_time"), "end": times.get("end_time")})
    return rows


def hmflow_runs(out: Path, rounds: int, size: int, tool: str = "hmflow") -> list[dict]:
    """Every journaled member run of an hmflow campaign, by iteration and member."""
    from storage import ArtifactStore, EvaluationJournal
    from storage.ensemble import member_journal

    store = ArtifactStore(out / "hmflow-store")
    rows = []
    for i in range(rounds):
        records = {r["index"]: r for r in
                   EvaluationJournal(store, VARIANTS[tool][1], member_journal(i)).rows()}
        for m in range(size):
            r = records.get(m)
            run_dir = Path(r["run_dir"]) if r and r.get("run_dir") else None
            found = sorted(run_dir.glob("*.SMSPEC")) if run_dir and run_dir.is_dir() else []
            ok = r is not None and r.get("status") != "FAIL" and bool(found)
            start = r["finished_at"] - r["wall_time_s"] if r else None
            rows.append({"tool": tool, "iteration": i, "member": m,
                         "run_dir": str(run_dir) if run_dir else None, "ran": r is not None,
                         "ok": ok, "summary": str(found[0]) if ok else None,
                         "failure": (r or {}).get("failure"), "start": start,
                         "end": r["finished_at"] if r else None})
    return rows


def score_runs(runs: list[dict], obs: ObservationSet, wells: list[str]) -> tuple[pd.DataFrame,
                                                                                 dict]:
    """Each run's misfits and values at the schedule's end (module doc, step 4); and the
    curves of each run by (tool, iteration, member)."""
    idx = obs.vector_index("fit")
    observed = obs.rows.observed.to_numpy(float)
    sigma = obs.rows.sigma.to_numpy(float)
    curves = {}
    for r in runs:
        r.update(misfit_diag=np.nan, misfit_ar1=np.nan, unmatched=np.nan)
        if not r["ok"]:
            continue
        responses = read_responses(Path(r["summary"]), wells)
        z = (obs.simulated(responses) - observed) / sigma
        r["unmatched"] = int(np.isnan(z[idx]).sum())
        r["misfit_diag"] = float(np.nanmean(z[idx] ** 2))
        r["misfit_ar1"] = float(np.mean(obs.whiten(z, "fit") ** 2))
        c = read_curves(Path(r["summary"]), wells)
        curves[(r["tool"], r["iteration"], r["member"])] = c
        end = c[c.days == c.days.max()]
        for _, row in end[end.quantity.isin(["FOPT", "WOPT"])].iterrows():
            r[f"{row.well}_{row.quantity}" if row.well != "FIELD" else row.quantity] = \
                float(row.value)
    return pd.DataFrame(runs), curves


def read_fields(files: dict[str, Path], case, grid) -> dict[str, np.ndarray] | None:
    """{field name: update-space values (n_active,)} from ``files[field name]`` (a GRDECL file
    holding the field's keyword); None when a file is missing."""
    out = {}
    for f in case.fields:
        path = files.get(f.name)
        if path is None or not path.is_file():
            return None
        values = read_grdecl(path)[f.keyword]
        values = values[grid.active] if values.size == grid.n_total else values
        out[f.name] = to_update_space(np.asarray(values, float), f)
    return out


def field_errors(case, grid, truth_grdecl: Path, ensembles: dict[str, list[dict]]) -> list[dict]:
    """RMSE of each ensemble's mean field to the truth and its mean spread, per field."""
    truth_arrays = read_grdecl(truth_grdecl)
    rows = []
    for label, members in ensembles.items():
        for f in case.fields:
            t = truth_arrays[f.keyword]
            t = to_update_space(np.asarray(t[grid.active] if t.size == grid.n_total else t,
                                           float), f)
            X = np.array([m[f.name] for m in members if m is not None])
            if X.size == 0:
                continue
            rows.append({"ensemble": label, "field": f.name,
                         "space": "log10" if f.in_log else "value", "members": len(X),
                         "rmse_mean": float(np.sqrt(np.mean((X.mean(axis=0) - t) ** 2))),
                         "spread": float(X.std(axis=0, ddof=1).mean())})
    return rows


def percentile_of(values: np.ndarray, truth: float) -> float:
    """The share of members below the truth, in % (where the truth falls in the ensemble)."""
    values = values[np.isfinite(values)]
    return float(100.0 * np.mean(values < truth)) if values.size else float("nan")


def ert_report(out: Path) -> dict:
    """What ERT told its user: the last lines of its output and its update logs' counts of
    active and deactivated observations."""
    log = out / "ert" / "ert.log"
    text = log.read_text(errors="replace") if log.is_file() else ""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    updates = []
    for path in sorted((out / "ert" / "update_log").glob("*/Report.csv"),
                       key=lambda p: p.stat().st_mtime):
        report = pd.read_csv(path)
        updates.append({"log": str(path), "observations": len(report),
                        "status": {str(k): int(v) for k, v in
                                   report.status.value_counts().items()},
                        "obs_error_scaling": sorted(set(np.round(
                            report.obs_error_scaling.astype(float), 4).tolist())),
                        "missing_realizations": sorted({
                            str(x) for x in report.missing_realizations.dropna()})})
    monitor = ("Waiting", "Pending", "Running", "Failed", "Finished", "Unknown", "-->", "|")
    said = [ln.strip() for ln in lines if not ln.strip().startswith(monitor)
            and "Running time" not in ln]
    return {"tail": said[-25:], "updates": updates}


def hmflow_report(out: Path, tool: str = "hmflow") -> dict:
    log = out / f"{tool}.log"
    lines = [ln for ln in (log.read_text(errors="replace") if log.is_file() else "").splitlines()
             if ln.strip()]
    doc = {"tail": lines[-25:]}
    try:
        from storage import ArtifactStore
        from storage.ensemble import FORECAST_STEP

        summary = ArtifactStore(out / "hmflow-store").latest(
            VARIANTS[tool][1], FORECAST_STEP).read_json("summary.json")
        doc.update({k: summary.get(k) for k in ("headline", "runs", "failed", "iterations",
                                                 "updates")})
    except Exception as exc:  # noqa: BLE001 - the report is best effort
        doc["summary_error"] = f"{type(exc).__name__}: {exc}"
    return doc


def compare(case_path: Path, out: Path, results: Path, name: str, seed: int = 0) -> dict:
    case = load_case(case_path)
    grid = read_grid(case.deck)
    size = case.ensemble.size
    rounds = len(case.ensemble.alphas) + 1
    wells = sorted(case.info.wells)
    obs = ObservationSet.from_case(case)
    truth_doc = json.loads((case_path.parent / "hidden_truth.json").read_text())
    truth = {(t["well"], t["quantity"]): float(t["value"]) for t in truth_doc["forecast"]}
    tools = ["ert", *[t for t in VARIANTS if (out / f"{t}.json").is_file()]]
    runs = ert_runs(out, rounds, size)
    for tool in tools[1:]:
        runs += hmflow_runs(out, rounds, size, tool)
    table, curves = score_runs(runs, obs, wells)

    prior_files = [{f.name: out / "prior" / f"{f.name}_{m}.grdecl" for f in case.fields}
                   for m in range(size)]
    prior = [read_fields(files, case, grid) for files in prior_files]
    last = rounds - 1
    ert_post = [read_fields({f.name: out / "ert" / "simulations" / f"realization-{m}" /
                             f"iter-{last}" / f"{f.name}.grdecl" for f in case.fields},
                            case, grid) for m in range(size)]
    ensembles = {"prior": prior, "ert posterior": ert_post}
    for tool in tools[1:]:
        dirs = table[(table.tool == tool) & (table.iteration == last)].run_dir
        ensembles[f"{tool} posterior"] = [
            read_fields({f.name: Path(d) / "FIELDS.GRDECL" for f in case.fields}, case, grid)
            if isinstance(d, str) else None for d in dirs]
    fields = field_errors(case, grid, Path(truth_doc["truth_grdecl"]), ensembles)

    timing = {tool: json.loads(p.read_text()) if p.is_file() else None
              for tool, p in (("ert", out / "ert" / "run.json"),
                              *((t, out / f"{t}.json") for t in tools[1:]))}
    summary = []
    for tool in tools:
        t = table[table.tool == tool]
        spans = [float(g.end.max() - g.start.min()) for _, g in t.groupby("iteration")
                 if g.start.notna().any()]
        # the runs' own time (ERT: its forward model's, in whole seconds; hmflow: the
        # simulate task's) per worker, against the round's wall time
        busy = [float((g.end - g.start).sum()) / WORKERS for _, g in t.groupby("iteration")
                if g.start.notna().any()]
        wall = (timing[tool] or {}).get("wall_s")
        entry = {"tool": tool, "simulations": int(t.ran.sum()),
                 "failed": int((t.ran & ~t.ok).sum()),
                 "not_run": int((~t.ran).sum()),
                 "wall_s": wall, "returncode": (timing[tool] or {}).get("returncode"),
                 "runs_wall_s": [round(x, 1) for x in spans],
                 "runs_busy_per_worker_s": [round(x, 1) for x in busy],
                 "runs_overhead": (sum(spans) / sum(busy) - 1.0) if sum(busy) else None,
                 "outside_runs_s": wall - sum(spans) if wall is not None else None}
        for label, i in (("prior", 0), ("posterior", last)):
            s = t[(t.iteration == i) & t.ok]
            entry[f"{label}_runs_ok"] = len(s)
            for col in ("misfit_diag", "misfit_ar1"):
                entry[f"{label}_{col}_median"] = float(s[col].median()) if len(s) else None
                entry[f"{label}_{col}_mean"] = float(s[col].mean()) if len(s) else None
            band = forecast_table({m: curves[(tool, i, m)] for m in s.member}, wells)
            for _, b in band.iterrows():
                key = "FOPT" if b.well == "FIELD" else f"{b.well}_WOPT"
                if b.quantity not in ("FOPT", "WOPT"):
                    continue
                tv = truth.get((b.well, b.quantity))
                entry[f"{label}_{key}"] = {
                    "P90": b.P90, "P50": b.P50, "P10": b.P10, "members": int(b.members),
                    "truth": tv, "inside": bool(b.P90 <= tv <= b.P10) if tv is not None else None,
                    "truth_percentile": percentile_of(s[key].to_numpy(float), tv)
                    if tv is not None and key in s else None,
                    "width_over_p50": (b.P10 - b.P90) / b.P50}
        for row in fields:
            if row["ensemble"] in ("prior", f"{tool} posterior"):
                label = "prior" if row["ensemble"] == "prior" else "posterior"
                entry[f"{label}_{row['field']}_rmse"] = row["rmse_mean"]
                entry[f"{label}_{row['field']}_spread"] = row["spread"]
        summary.append(entry)

    doc = {"name": name, "case": str(case_path), "out": str(out),
           "date": dt.date.today().isoformat(), "machine": machine(),
           "ensemble": case.ensemble.model_dump(mode="json"), "rounds": rounds,
           "seed": seed, "ert_random_seed": seed or 123456789,
           "observations": {"rows": len(obs.vector_index("fit")), "rho": obs.rho},
           "truth_FOPT": truth.get(("FIELD", "FOPT")), "summary": summary, "fields": fields,
           "timing": timing, "ert_report": ert_report(out),
           **{f"{t}_report": hmflow_report(out, t) for t in tools[1:]},
           "versions": versions()}
    results.mkdir(parents=True, exist_ok=True)
    (results / f"{name}.json").write_text(json.dumps(doc, indent=2, default=_jsonable) + "\n")
    keep = ["tool", "iteration", "member", "ran", "ok", "misfit_diag", "misfit_ar1",
            "unmatched", "FOPT", *[f"{w}_WOPT" for w in wells]]
    table[[c for c in keep if c in table]].to_csv(results / f"{name}-members.csv", index=False)
    flat = pd.DataFrame([{k: (v if not isinstance(v, dict) else None) for k, v in e.items()}
                         for e in summary]).dropna(axis=1, how="all")
    for e, row in zip(summary, range(len(summary))):
        for label in ("prior", "posterior"):
            band = e.get(f"{label}_FOPT")
            if band:
                for k in ("P90", "P50", "P10", "inside", "truth_percentile"):
                    flat.loc[row, f"{label}_FOPT_{k}"] = band[k]
    flat.to_csv(results / f"{name}-table.csv", index=False)
    print(markdown(doc))
    return doc


def _jsonable(x):
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return str(x)


def machine() -> dict:
    return {"cores": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "memory_gib": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
                                / 2 ** 30, 1)}


def versions() -> dict:
    from importlib.metadata import version

    out = {"python_hmflow": platform.python_version()}
    for pkg in ("opm", "opm-simulators", "iterative_ensemble_smoother", "hmflow"):
        try:
            out[pkg] = version(pkg)
        except Exception:  # noqa: BLE001
            out[pkg] = None
    return out


def markdown(doc: dict) -> str:
    s = {e["tool"]: e for e in doc["summary"]}
    tools = [t for t in ("ert", *VARIANTS) if t in s]

    def cell(tool: str, key: str, fmt: str = "{:.3g}") -> str:
        v = s[tool].get(key)
        return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else fmt.format(v)

    def band(tool: str, label: str, key: str = "FOPT") -> str:
        b = s[tool].get(f"{label}_{key}")
        if not b:
            return "-"
        return (f"{b['P90'] / 1e6:.3f} / {b['P50'] / 1e6:.3f} / {b['P10'] / 1e6:.3f} "
                f"({'inside' if b['inside'] else 'OUTSIDE'}, at P{100 - b['truth_percentile']:.0f})")

    lines = [f"## {doc['name']}: truth FOPT {doc['truth_FOPT'] / 1e6:.4f} e6 sm3", "",
             "| | " + " | ".join(tools) + " |", "|---|" + "---|" * len(tools)]
    rows = [("data misfit, prior runs (median, diagonal sigma)", "prior_misfit_diag_median"),
            ("data misfit, posterior runs (median, diagonal sigma)", "posterior_misfit_diag_median"),
            ("data misfit, posterior runs (mean, diagonal sigma)", "posterior_misfit_diag_mean"),
            ("data misfit, prior runs (median, hmflow's AR(1))", "prior_misfit_ar1_median"),
            ("data misfit, posterior runs (median, hmflow's AR(1))", "posterior_misfit_ar1_median"),
            ("RMSE posterior mean PORO to truth", "posterior_poro_rmse"),
            ("RMSE posterior mean log10 PERMX to truth", "posterior_permx_rmse"),
            ("spread posterior PORO", "posterior_poro_spread"),
            ("spread posterior log10 PERMX", "posterior_permx_spread")]
    for label, key in rows:
        lines.append(f"| {label} | " + " | ".join(cell(t, key) for t in tools) + " |")
    lines.append("| FOPT prior P90 / P50 / P10 (e6 sm3) | "
                 + " | ".join(band(t, "prior") for t in tools) + " |")
    lines.append("| FOPT posterior P90 / P50 / P10 (e6 sm3) | "
                 + " | ".join(band(t, "posterior") for t in tools) + " |")
    for label in ("prior", "posterior"):
        lines.append(f"| {label}: truth inside P90-P10 of FOPT and the wells' WOPT | " + " | ".join(
            f"{sum(bool(v['inside']) for k, v in s[t].items() if k.startswith(label + '_') and isinstance(v, dict))}"
            f" of {sum(1 for k, v in s[t].items() if k.startswith(label + '_') and isinstance(v, dict))}"
            for t in tools) + " |")
    lines.append("| simulations (failed) | " + " | ".join(
        f"{s[t]['simulations']} ({s[t]['failed']})" for t in tools) + " |")
    lines.append("| wall time of the command (s) | " + " | ".join(
        cell(t, "wall_s", "{:.0f}") for t in tools) + " |")
    lines.append("| of which the 4 rounds of runs (s) | " + " | ".join(
        " + ".join(f"{x:.0f}" for x in s[t]["runs_wall_s"]) for t in tools) + " |")
    lines.append("| the runs' own time per worker (s) | " + " | ".join(
        " + ".join(f"{x:.0f}" for x in s[t]["runs_busy_per_worker_s"]) for t in tools) + " |")
    lines.append("| rounds' wall time over the runs' own time | " + " | ".join(
        cell(t, "runs_overhead", "{:+.0%}") for t in tools) + " |")
    prior = {(r["field"]): r for r in doc["fields"] if r["ensemble"] == "prior"}
    lines.append("")
    lines.append("prior mean RMSE to truth: " + ", ".join(
        f"{f} {r['rmse_mean']:.4f} (spread {r['spread']:.4f})" for f, r in prior.items()))
    return "\n".join(lines)


def aggregate(results: Path, names: list[str]) -> str:
    """One row per run (tool and seed) of the results ``names`` (their JSON files in
    ``results``) and the mean over seeds per tool, as Markdown; written to
    ``results/seeds.csv``."""
    rows = []
    for name in names:
        doc = json.loads((results / f"{name}.json").read_text())
        for e in doc["summary"]:
            band = e.get("posterior_FOPT") or {}
            inside = [v["inside"] for k, v in e.items()
                      if k.startswith("posterior_") and isinstance(v, dict)]
            rows.append({"tool": e["tool"], "seed": doc.get("seed", 0),
                         "misfit_diag": e["posterior_misfit_diag_median"],
                         "misfit_ar1": e["posterior_misfit_ar1_median"],
                         "fopt_p90": band.get("P90"), "fopt_p50": band.get("P50"),
                         "fopt_p10": band.get("P10"), "fopt_inside": band.get("inside"),
                         "fopt_truth_percentile": band.get("truth_percentile"),
                         "width_over_p50": band.get("width_over_p50"),
                         "inside_of_5": sum(map(bool, inside)),
                         "rmse_poro": e.get("posterior_poro_rmse"),
                         "rmse_log10_permx": e.get("posterior_permx_rmse"),
                         "spread_poro": e.get("posterior_poro_spread"),
                         "spread_log10_permx": e.get("posterior_permx_spread"),
                         "simulations": e["simulations"], "failed": e["failed"],
                         "wall_s": e["wall_s"], "runs_overhead": e.get("runs_overhead")})
    table = pd.DataFrame(rows).sort_values(["tool", "seed"])
    table.to_csv(results / "seeds.csv", index=False)
    cols = ["misfit_diag", "misfit_ar1", "fopt_p50", "width_over_p50", "inside_of_5",
            "rmse_poro", "rmse_log10_permx", "spread_poro", "spread_log10_permx", "wall_s",
            "runs_overhead"]
    mean = table.groupby("tool")[cols].mean()
    lines = [("| tool | seed | misfit (diag) | misfit (AR1) | FOPT P90/P50/P10 e6 | truth in "
              "FOPT band | wells+FOPT inside | RMSE poro | RMSE log10 k | wall s | "
              "run overhead |"), "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table.itertuples():
        lines.append(f"| {r.tool} | {r.seed} | {r.misfit_diag:.2f} | {r.misfit_ar1:.2f} | "
                     f"{r.fopt_p90 / 1e6:.3f}/{r.fopt_p50 / 1e6:.3f}/{r.fopt_p10 / 1e6:.3f} | "
                     f"{'yes' if r.fopt_inside else 'NO'} (P{100 - r.fopt_truth_percentile:.0f}) | "
                     f"{r.inside_of_5} of 5 | {r.rmse_poro:.4f} | {r.rmse_log10_permx:.3f} | "
                     f"{r.wall_s:.0f} | {r.runs_overhead:+.0%} |")
    for tool, r in mean.iterrows():
        n = int((table.tool == tool).sum())
        lines.append(f"| **{tool}, mean of {n}** | | {r.misfit_diag:.2f} | {r.misfit_ar1:.2f} | "
                     f"P50 {r.fopt_p50 / 1e6:.3f}, width {r.width_over_p50:.1%} of P50 | | "
                     f"{r.inside_of_5:.1f} of 5 | {r.rmse_poro:.4f} | {r.rmse_log10_permx:.3f} | "
                     f"{r.wall_s:.0f} | {r.runs_overhead:+.0%} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=Path, default=Path("/work/bench/calib/truth-1/case.toml"))
    ap.add_argument("--out", type=Path, default=Path("/work/bench/ert/synthetic-truth-1"))
    ap.add_argument("--ert", type=Path, default=Path("/work/ert26-venv/bin/ert"),
                    help="the ert command of ERT's own environment")
    ap.add_argument("--stage", choices=["all", "prepare", "ert", "hmflow", "hmflow-white",
                                        "compare", "aggregate"], default="all",
                    help="all: prepare, ert, hmflow, compare (hmflow-white, the ablation, "
                         "only when asked)")
    ap.add_argument("--results", type=Path, default=REPO / "benchmarks" / "results" / "ert")
    ap.add_argument("--seed", type=int, default=0,
                    help="ERT's RANDOM_SEED and hmflow's [ensemble] seed (the observation "
                         "perturbations); 0: ERT 123456789, hmflow the case's")
    ap.add_argument("--name", default=None, help="results' file name (default: OUT's name)")
    ap.add_argument("--aggregate", nargs="*", default=[], metavar="NAME",
                    help="with --stage aggregate: the results (names) to put in one table")
    args = ap.parse_args()
    if args.stage == "aggregate":
        print(aggregate(args.results.resolve(), args.aggregate))
        return
    case_path, out = args.case.resolve(), args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    name = args.name or out.name
    if args.stage in ("all", "prepare"):
        print(json.dumps(prepare(case_path, out, args.seed), indent=2))
    if args.stage in ("all", "ert"):
        run_ert(args.ert, out, load_case(case_path).ensemble.weights)
    if args.stage in ("all", "hmflow"):
        run_hmflow(out)
    if args.stage == "hmflow-white":
        run_hmflow(out, "hmflow-white")
    if args.stage in ("all", "compare"):
        compare(case_path, out, args.results.resolve(), name, args.seed)


if __name__ == "__main__":
    main()
