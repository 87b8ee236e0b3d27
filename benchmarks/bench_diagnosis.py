"""Hidden-effect sweep of the diagnosis: hit rate per kind, gain, simulator calls and wall time.

    python benchmarks/bench_diagnosis.py --case synthetic --kinds all --seeds 11 12 \\
        --controls 6 7 [--workers 2] [--json out.json]
    python benchmarks/bench_diagnosis.py --case punq --kinds all --seeds 21
    python benchmarks/bench_diagnosis.py --case punq --record-end 0 --history-end 0  # as `hide`
    python benchmarks/bench_diagnosis.py --case punq-real        # PUNQ-S3's measured history
    python benchmarks/bench_diagnosis.py --case synthetic --kinds generators --seeds 31 32 33 \
        --jsonl benchmarks/results/diagnosis-sweep/synthetic.jsonl   # issue 18's sweep
    python benchmarks/bench_diagnosis.py --case punq --kinds generators --seeds 31 32 33 \
        --record-end 0 --history-end 0 --jsonl benchmarks/results/diagnosis-sweep/punqs3.jsonl
    python benchmarks/bench_diagnosis.py --table benchmarks/results/diagnosis-sweep/*.jsonl \
        [--into docs/diagnosis.md]

For each (kind, seed) a case is written whose truth hides one extension drawn by the seed
(:mod:`hmcore.scenarios.hidden`): the synthetic case (seeded fields and noise, the known
five-parameter truth) or PUNQ-S3 (truth run of PUNQS3.DATA with the effect applied, PUNQ-style
AR(1) noise, no sigma in the CSV, record to day 2936, fitted to day 2200; ``--record-end 0
--history-end 0``: `hmflow hide`'s defaults, the whole schedule, 75 % of it fitted). The diagnosis runs on
the base model, ``workers`` simulations at a time, and is judged by
:func:`hmcore.scenarios.judge.judge`: right kind (and well / layer / plane) ranked first,
selected, held-back misfit improved. Controls hide nothing and must report ``none``.
``--kinds generators``: the effects beyond the library's geometry
(:mod:`hmcore.scenarios.generators`), judged by :func:`hmcore.scenarios.judge.judge_effects`
(each effect named by an accepted cause, its family and wells; an effect of no family:
``unexplained``, or ``none`` when the fitted history hardly shows it).
``--jsonl FILE``: one line per case, appended as each ends; a rerun skips the cases the file
already holds (a sweep runs in slices across sessions). ``--keep DIR``: each case's hidden
effect, report and diagnosis JSON (gzipped) copied to ``DIR/<case>-<kind>-<seed>/``;
``--rejudge --jsonl FILE --keep DIR`` judges the rows again from them (after a change of the
judge, not of the diagnosis; the answer's lead is set again first,
:func:`hmcore.diagnosis.decision.lead_unexplained`, which reorders the stored causes and runs
nothing - a row it changed says ``lead``). ``--table FILE...``: the markdown
table of such files; with ``--into DOC`` it replaces the text between the lines
``<!-- sweep table -->`` and ``<!-- end sweep table -->`` of DOC (docs/diagnosis.md) instead of
printing it. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PUNQ = Path(__file__).resolve().parents[2] / "shared" / "punqs3"
PUNQ_TRUTH = {"poro_mult": 1.0, "permx_mult": 1.0, "permy_mult": 1.0, "permz_mult": 1.0,
              "skin": 5.0}


def one(case: str, kind: str | None, seed: int, root: Path, workers: int,
        history_end: float = 2200.0, record_end: float = 2936.0) -> dict:
    from hmcore.cases import load_case
    from hmcore.diagnosis import diagnose, local_evaluator
    from hmcore.scenarios.hidden import write_hidden_deck_case, write_hidden_synthetic_case

    tmp = root / f"{case}-{kind or 'control'}-{seed}"
    t0 = time.perf_counter()
    if case == "synthetic":
        toml, _ = write_hidden_synthetic_case(tmp / "case", seed, kind)
    elif case == "punq":
        toml, _ = write_hidden_deck_case(tmp / "case", PUNQ / "PUNQS3.DATA", seed,
                                              truth=PUNQ_TRUTH, kind=kind,
                                              history_end_days=history_end or None,
                                              with_sigma=False, end_days=record_end or None,
                                              name="punq-hidden")
    else:
        tmp.mkdir(parents=True, exist_ok=True)
        toml = tmp / "case.toml"
        toml.write_text(f'[case]\nname = "punqs3"\ndeck = "{PUNQ / "PUNQS3.DATA"}"\n'
                        f'observed = "{PUNQ / "punqs3_observed_full_history.csv"}"\n'
                        "history_end_days = 2200\n")
    doc = diagnose(load_case(toml), local_evaluator(tmp / "runs", workers), out_dir=tmp / "out")
    wall = time.perf_counter() - t0
    shutil.rmtree(tmp / "runs", ignore_errors=True)
    if case != "punq-real":
        out = judged(doc, tmp / "case" / "hidden_effect.json")
    else:
        out = {"ranking": [f"{c['id']} ({c['chi2']:.0f})" for c in doc["causes"][:5]
                           if c["chi2"] is not None], "verdict": doc["verdict"],
               "gain": doc["gain"], "hidden_values": {}}
    out["accepted_gains"] = [{"id": a["id"], "round": a["round"], **a["gain"]}
                             for a in doc.get("accepted") or []]
    out["named_on"] = doc.get("named_on")
    out.update({"case": case, "kind": kind or "control", "seed": seed, "wall_s": wall,
                "commit": _commit(),
                "simulations": doc["cost"]["simulations"], "out": str(tmp / "out"),
                "selected": out.get("selected", doc["selected"] and doc["selected"]["id"])})
    return out


def judged(doc: dict, hidden_path: Path) -> dict:
    """The judgement of a diagnosis ``doc`` against the hidden effect(s) of ``hidden_path``
    (:func:`hmcore.scenarios.judge.judge_effects` for generated or several effects,
    :func:`~hmcore.scenarios.judge.judge` for one library effect), with the effect's signal."""
    from hmcore.scenarios.judge import judge, judge_effects, visible
    from hmcore.scenarios.effects import load_hidden_effects

    signal = json.loads(hidden_path.read_text()).get("signal") or {}
    effects = load_hidden_effects(hidden_path)
    generated = any(e.generated for e in effects) or len(effects) > 1
    out = (judge_effects(doc, effects, signal) if generated
           else judge(doc, effects[0] if effects else None, signal))
    out.update({"signal_fit": signal.get("chi2_fit"), "signal_heldout": signal.get("chi2_heldout"),
                "signal_fit_after_globals": signal.get("chi2_fit_after_globals"),
                "visible": visible(signal) if signal else None,
                "visible_in_fitted_history": signal.get("visible_in_fitted_history"),
                "truth_E_heldout": signal.get("truth_E_heldout"),
                "lead": doc.get("lead"),
                "first_cause": doc["causes"][0]["id"] if doc.get("causes") else None,
                "hidden_values": {e.candidate.id: e.value for e in effects}})
    return out



def keep(row: dict, into: Path) -> Path:
    """Copy a case's evidence - its hidden effect, the diagnosis report and its JSON
    (gzipped) - to ``into/<case>-<kind>-<seed>/``, so the sweep can be judged again
    (``--rejudge``) and read after the temporary folders are gone."""
    import gzip

    out = Path(row["out"])
    dest = into / f"{row['case']}-{row['kind']}-{row['seed']}"
    dest.mkdir(parents=True, exist_ok=True)
    hidden = out.parent / "case" / "hidden_effect.json"
    if hidden.is_file():
        shutil.copy2(hidden, dest / "hidden_effect.json")
    if (out / "report.md").is_file():
        shutil.copy2(out / "report.md", dest / "report.md")
    if (out / "diagnosis.json").is_file():
        with gzip.open(dest / "diagnosis.json.gz.tmp", "wb", compresslevel=9) as fh:
            fh.write((out / "diagnosis.json").read_bytes())
        (dest / "diagnosis.json.gz.tmp").replace(dest / "diagnosis.json.gz")
    return dest


def rejudge(jsonl: Path, kept: Path) -> int:
    """Judge every row of ``jsonl`` again from its kept evidence (after a change of the judge,
    not of the diagnosis) and rewrite the file (atomically). Returns the rows judged."""
    import gzip

    from hmcore.diagnosis.decision import lead_unexplained

    rows, n = _read_jsonl(jsonl), 0
    for r in rows:
        dest = kept / f"{r['case']}-{r['kind']}-{r['seed']}"
        if r.get("error") or not (dest / "diagnosis.json.gz").is_file() or \
                not (dest / "hidden_effect.json").is_file():
            continue
        doc = json.loads(gzip.decompress((dest / "diagnosis.json.gz").read_bytes()))
        doc = lead_unexplained(doc, _settings_of(doc))
        r.update(judged(doc, dest / "hidden_effect.json"))
        n += 1
    tmp = jsonl.with_suffix(".tmp")
    tmp.write_text("".join(json.dumps(r, default=str) + "\n" for r in rows))
    tmp.replace(jsonl)
    return n


def _settings_of(doc: dict):
    """The settings a stored diagnosis ran with, as far as :func:`rejudge` needs them (the
    held-back noise line and the partial share; the defaults where the document predates
    one)."""
    from hmcore.diagnosis.settings import DiagnosisSettings

    stored, s = doc.get("settings") or {}, DiagnosisSettings()
    return DiagnosisSettings(quiet_sd=float(stored.get("quiet_sd", s.quiet_sd)),
                             partial_share=float(stored.get("partial_share", s.partial_share)))


def _commit() -> str | None:
    """The code's git commit (None outside a checkout), so a row says what made it."""
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10, cwd=Path(__file__).resolve().parent
                              ).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def _read_jsonl(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _fmt(x, spec: str = ".3g") -> str:
    return "-" if x is None else format(x, spec)


def _found(r: dict) -> str:
    """yes / no; for an effect the data hardly show (``visible`` false: its signal, once the
    globals absorb what they can, under the line on the fitted history and under the held-back
    noise line on the held-back one: :func:`hmcore.scenarios.judge.visible`), ``none`` is
    right too. A wrong
    answer whose model predicts the held-back history about as well as the truth (E within
    10 % of the truth's) is marked so: the data do not tell the two apart."""
    if r.get("found"):
        return "yes"
    if r.get("visible") is False:
        return "invisible: none (right)" if not r.get("accepted") else "invisible: wrong name"
    gains, truth = r.get("accepted_gains") or [], r.get("truth_E_heldout")
    if gains and truth and gains[-1]["heldout_after"] is not None \
            and gains[-1]["heldout_after"] <= 1.1 * truth:
        return (f"no: another model as good as the truth (held-back E "
                f"{gains[-1]['heldout_after'] / truth:.2f}x the truth's)")
    return "no"


def _outcome(r: dict) -> str:
    """The answer by the evidence (:func:`hmcore.scenarios.judge.answer_outcome`): right,
    honest or wrong, with its set size; '-' for a row judged before it was recorded."""
    return f"{r['outcome']} ({r.get('set_size', 1)})" if r.get("outcome") else "-"


def _outcomes(rows: list[dict]) -> str:
    """Right / honest / wrong counts of ``rows`` and their mean set size."""
    got = [r for r in rows if r.get("outcome")]
    if not got:
        return "-"
    count = {k: sum(r["outcome"] == k for r in got) for k in ("right", "honest", "wrong")}
    size = sum(r.get("set_size", 1) for r in got) / len(got)
    return f"{count['right']} / {count['honest']} / {count['wrong']} ({size:.1f})"


def table(rows: list[dict]) -> str:
    """The markdown table of sweep rows: one line per case, then one per (case, kind); in the
    order case, kind (controls, then the generators in their order, then library kinds), seed."""
    from hmcore.scenarios.generators import GENERATORS

    order = {k: i for i, k in enumerate(("control", *GENERATORS))}
    rows = sorted(rows, key=lambda r: (r["case"] != "synthetic", r["case"],
                                       order.get(r["kind"], len(order)), r["kind"], r["seed"]))
    lines = ["| case | kind | seed | hidden (value) | signal chi2 fit / after globals | "
             "answer (window) | accepted: held-back E before -> after | found | by the evidence "
             "(set size) | sims | min |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        hidden = ", ".join(f"{k} ({v:.3g})" for k, v in (r.get("hidden_values") or {}).items())
        gains = "; ".join(f"{a['id']}: {_fmt(a['heldout_before'], '.4f')} -> "
                          f"{_fmt(a['heldout_after'], '.4f')}"
                          for a in r.get("accepted_gains") or []) or "-"
        first = (r.get("ranking") or ["-"])[0]
        answer = (f"first {r['first_cause']}" if r.get("first_cause") and not r.get("error")
                  else (r.get("verdict") or r.get("error") or "-").split(":")[0][:40])
        win = r.get("named_on")
        win = (f"named on the window to day {win['fitted_to_day']:g}" if isinstance(win, dict)
               else "first window")
        lines.append(
            f"| {r['case']} | {r['kind']} | {r['seed']} | {hidden or '-'} | "
            f"{_fmt(r.get('signal_fit'), '.0f')} / {_fmt(r.get('signal_fit_after_globals'), '.0f')}"
            f" | {answer}; top score {first} ({win}) | {gains} | "
            f"{_found(r)} | {_outcome(r)} | {r.get('simulations', '-')} | "
            f"{_fmt((r.get('wall_s') or 0) / 60, '.1f')} |")
    lines += ["", "| case | kind | cases | visible | found (of the visible) | right answers "
                  "(none on an invisible one counts) | by the evidence, of the visible: right / "
                  "honest / wrong (mean set size) | mean simulations |",
              "|---|---|---|---|---|---|---|---|"]
    for key in dict.fromkeys((r["case"], r["kind"]) for r in rows):
        sub = [r for r in rows if (r["case"], r["kind"]) == key]
        n, seen = len(sub), [r for r in sub if r.get("visible") is not False]
        right = sum(_found(r) in ("yes", "invisible: none (right)") for r in sub)
        lines.append(f"| {key[0]} | {key[1]} | {n} | {len(seen)}/{n} | "
                     f"{sum(bool(r.get('found')) for r in seen)}/{len(seen)} | {right}/{n} | "
                     f"{_outcomes(seen)} | "
                     f"{sum(r.get('simulations', 0) for r in sub) / n:.0f} |")
    return "\n".join(lines) + "\n"


TABLE_START, TABLE_END = "<!-- sweep table -->", "<!-- end sweep table -->"


def into_doc(doc: Path, text: str) -> None:
    """Put ``text`` between the lines TABLE_START and TABLE_END of ``doc`` (written to a
    temporary file beside it, then moved into place); the rest of the file is kept as it is."""
    lines = doc.read_text(encoding="utf-8").splitlines(keepends=True)
    starts = [i for i, line in enumerate(lines) if line.strip() == TABLE_START]
    ends = [i for i, line in enumerate(lines) if line.strip() == TABLE_END]
    if len(starts) != 1 or len(ends) != 1 or ends[0] < starts[0]:
        raise SystemExit(
            f"{doc}: the table goes between one line {TABLE_START} and one later line "
            f"{TABLE_END}; found {len(starts)} and {len(ends)} (fix: put the two lines where "
            f"the table belongs)")
    new = lines[:starts[0] + 1] + [text if text.endswith("\n") else text + "\n"] + lines[ends[0]:]
    tmp = doc.with_name(f".{doc.name}.tmp")
    tmp.write_text("".join(new), encoding="utf-8")
    tmp.replace(doc)


def main() -> None:
    from hmcore.diagnosis.candidate import KINDS
    from hmcore.scenarios.generators import GENERATORS

    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=("synthetic", "punq", "punq-real"), default="synthetic")
    ap.add_argument("--kinds", nargs="+", default=["all"],
                    help="library kinds or generators; 'all': the library's kinds, "
                         "'generators': every generator")
    ap.add_argument("--seeds", nargs="*", type=int, default=[11, 12])
    ap.add_argument("--controls", nargs="*", type=int, default=[])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--root", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--jsonl", type=Path, help="append one line per case; skip those it holds")
    ap.add_argument("--table", type=Path, nargs="+", help="print the table of these JSONL files")
    ap.add_argument("--into", type=Path, help="with --table: write it into this markdown file "
                    f"between the lines {TABLE_START} and {TABLE_END}")
    ap.add_argument("--keep", type=Path, help="copy each case's hidden effect, report and "
                                              "diagnosis JSON (gzipped) into this folder")
    ap.add_argument("--rejudge", action="store_true", help="judge the rows of --jsonl again "
                    "from the evidence in --keep, and rewrite the file")
    ap.add_argument("--history-end", type=float, default=2200.0,
                    help="punq: days fitted (0: 75 %% of the record, as `hmflow hide`)")
    ap.add_argument("--record-end", type=float, default=2936.0,
                    help="punq: last day of the measured record (0: the schedule's end)")
    args = ap.parse_args()
    if args.into and not args.table:
        ap.error("--into needs --table")
    if args.table:
        text = table([r for f in args.table for r in _read_jsonl(f)])
        if args.into:
            into_doc(args.into, text)
            print(f"table of {len(args.table)} file(s) written into {args.into}")
        else:
            print(text, end="")
        return
    if args.rejudge:
        if not (args.jsonl and args.keep):
            ap.error("--rejudge needs --jsonl and --keep")
        print(f"judged again: {rejudge(args.jsonl, args.keep)} rows of {args.jsonl}")
        return
    kinds = (list(KINDS) if args.kinds == ["all"] else
             list(GENERATORS) if args.kinds == ["generators"] else args.kinds)
    root = args.root or Path(tempfile.mkdtemp(prefix="hmflow-bench-diagnosis-"))
    jobs = ([(None, 0)] if args.case == "punq-real" else
            [(k, s) for k in kinds for s in args.seeds] + [(None, s) for s in args.controls])
    done = {(r["kind"], r["seed"]) for r in _read_jsonl(args.jsonl)} if args.jsonl else set()
    rows = []
    for kind, seed in jobs:
        if (kind or "control", seed) in done:
            continue
        try:
            row = one(args.case, kind, seed, root, args.workers, args.history_end,
                      args.record_end)
        except Exception as exc:  # report and go on: a sweep is a measurement
            row = {"case": args.case, "kind": kind or "control", "seed": seed,
                   "error": f"{type(exc).__name__}: {exc}", "found": False}
        rows.append(row)
        print(json.dumps({k: row.get(k) for k in ("case", "kind", "seed", "hidden", "found",
                                                   "ranked_first", "selected", "signal_fit",
                                                   "signal_heldout", "signal_fit_after_globals",
                                                   "visible", "wall_s",
                                                   "simulations", "ranking", "error")},
                         default=str), flush=True)
        if args.keep and not row.get("error"):
            keep(row, args.keep)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=2, default=str))
        if args.jsonl:
            args.jsonl.parent.mkdir(parents=True, exist_ok=True)
            with args.jsonl.open("a") as fh:
                fh.write(json.dumps(row, default=str) + "\n")
    if rows and args.case != "punq-real":
        print()
        print(table(rows), end="")
    print(f"\noutputs under {root}")


if __name__ == "__main__":
    main()
