"""How the diagnosis's empirical thresholds held on the generator sweep (issue 18).

    python benchmarks/diagnosis_thresholds.py benchmarks/results/diagnosis-sweep/evidence

Reads each kept case (``<case>-<kind>-<seed>/``: ``hidden_effect.json`` and the gzipped
``diagnosis.json`` that ``bench_diagnosis.py --keep`` stores) and, for the window and round 1
that gave the answer, asks of every recalibrated candidate whether it names a hidden effect
(:func:`hmcore.scenarios.hidden.names`; an effect of no family is named by no candidate) and
how each line treated it:

- the fit line (``fit_threshold``, from ``false_alarm``): candidates over it where there is
  nothing to find (a control, or an effect the fitted history hardly shows: false alarms of
  the line), right candidates under it (missed);
- the held-back rule (``heldout_threshold``, ``quiet_sd``, ``heldout_e_slack``): right
  candidates over the fit line that it vetoed, noise fits it confirmed, and wrong candidates
  it confirmed where an effect acts (stand-ins that predict part of it);
- the tie band (``tie_band``): cases whose top two recalibrated fits lie within it (the
  held-back history ordered them), and whether the top one was right; apart from them, the
  cases whose runner-up fitted better by more than the band but was passed over because the
  held-back rule did not confirm it;
- the screen (``screen_threshold``): candidates recalibrated only because they scored between
  it and the line, and how many of those were right or accepted;
- the weak lead (``weak_lead``): cases whose leading score test was under it.

Prints a markdown table (docs/diagnosis.md). Nothing simulates; nothing is asserted.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


@dataclass
class Tally:
    """One line's outcomes over the sweep: counts and the cases behind the notable ones."""

    cases: int = 0
    quiet: int = 0
    right_missed: list[str] = field(default_factory=list)
    noise_passed: list[str] = field(default_factory=list)
    right_vetoed: list[str] = field(default_factory=list)
    noise_confirmed: list[str] = field(default_factory=list)
    stand_ins: int = 0
    ties: list[tuple[str, str]] = field(default_factory=list)
    passed_over: list[tuple[str, str]] = field(default_factory=list)
    screened: list[tuple[str, bool, bool]] = field(default_factory=list)
    weak: list[str] = field(default_factory=list)


def load(case_dir: Path):
    """(hidden effects, diagnosis document) of a kept case, or None when it lacks either."""
    from hmcore.scenarios.effects import load_hidden_effects

    hidden, doc = case_dir / "hidden_effect.json", case_dir / "diagnosis.json.gz"
    if not (hidden.is_file() and doc.is_file()):
        return None
    return load_hidden_effects(hidden), json.loads(gzip.open(doc).read())


def tally(cases: list[Path]) -> Tally:
    from hmcore.scenarios.judge import described, names, visible

    t = Tally()
    for case_dir in cases:
        loaded = load(case_dir)
        if loaded is None:
            continue
        effects, doc = loaded
        t.cases += 1
        label = case_dir.name
        signal = json.loads((case_dir / "hidden_effect.json").read_text()).get("signal") or {}
        quiet = not effects or not visible(signal)
        t.quiet += quiet
        s = doc["settings"]
        causes = {c["id"]: c for c in doc["causes"]}
        recal = doc.get("candidates_recalibrated") or {}

        def right(cid: str) -> bool:
            cause = causes.get(cid)
            return cause is not None and any(names(described(cause, doc), e) for e in effects)

        for cid, r in recal.items():
            line = r.get("fit_line", s["fit_threshold"])
            ok = right(cid)
            if ok and not r["fit_beyond_noise"]:
                t.right_missed.append(f"{label}: {cid} ({r['delta_ssr_fit']:.1f} < {line:.1f})")
            if quiet and r["fit_beyond_noise"]:
                t.noise_passed.append(f"{label}: {cid}")
                if r["heldout_beyond_noise"]:
                    t.noise_confirmed.append(f"{label}: {cid}")
            if r["fit_beyond_noise"] and ok and not r["heldout_beyond_noise"]:
                t.right_vetoed.append(
                    f"{label}: {cid} (held-back SSR {r['delta_ssr_heldout']:+.0f}, E "
                    f"{r['heldout_before']:.4f} -> {r['heldout_after']:.4f})")
            if not quiet and not ok and r["fit_beyond_noise"] and r["heldout_beyond_noise"]:
                t.stand_ins += 1
        st = doc.get("statistic") or {}
        runner = st.get("vs_runner_up")
        if runner and not runner["apart"]:
            # within the band either way: a tie the held-back history ordered; further below:
            # the runner-up fitted better, but the held-back rule did not confirm it
            into = t.ties if runner["lr"] >= -s["tie_band"] else t.passed_over
            into.append((label, "right" if right(st["cause"]) else "wrong" if any(
                right(c) for c in recal) else "no right candidate"))
        ranking = doc["ranking"]
        by_id = {c["id"]: c for c in ranking["candidates"]}
        line = ranking["chi2_threshold"]
        accepted = {a["id"] for a in doc.get("accepted") or []}
        for cid in ranking["screened"]:
            chi2 = by_id.get(cid, {}).get("chi2")
            if chi2 is not None and chi2 < line and cid in recal:
                t.screened.append((f"{label}: {cid}", right(cid), cid in accepted))
        top = [c.get("chi2") for c in ranking["candidates"] if c.get("chi2") is not None]
        if top and max(top) < s["weak_lead"]:
            t.weak.append(label)
    return t


def table(t: Tally) -> str:
    n_screen = len(t.screened)
    rows = [
        ("fit line (`false_alarm` 0.003 -> `fit_threshold`)",
         f"over it in the {t.quiet} cases with nothing to find (controls, invisible effects): "
         f"{len(t.noise_passed)}; right candidates under it: {len(t.right_missed)}",
         "; ".join(t.noise_passed + t.right_missed) or "-"),
        ("held-back rule (`heldout_threshold` 6, `quiet_sd` 3, `heldout_e_slack` 0.25)",
         f"right candidates vetoed: {len(t.right_vetoed)}; noise fits confirmed: "
         f"{len(t.noise_confirmed)}; wrong candidates it confirmed where an effect acts (stand-"
         f"ins that predict part of it; the ranking decides among them): {t.stand_ins}",
         "; ".join(t.right_vetoed + t.noise_confirmed) or "-"),
        ("tie band (`tie_band` 10)",
         f"cases with the top two within it: {len(t.ties)}; the held-back history put a right "
         f"one first in {sum(v == 'right' for _, v in t.ties)}, a wrong one before a right one "
         f"in {sum(v == 'wrong' for _, v in t.ties)}. Cases whose runner-up fitted better by "
         f"more than the band but was not confirmed by the held-back history: "
         f"{len(t.passed_over)}; the cause chosen instead right in "
         f"{sum(v == 'right' for _, v in t.passed_over)}, wrong where a right one was recalibrated "
         f"in {sum(v == 'wrong' for _, v in t.passed_over)}",
         "; ".join(f"{c} ({v})" for c, v in t.ties) + " / passed over: "
         + ("; ".join(f"{c} ({v})" for c, v in t.passed_over) or "-")),
        ("screen (`screen_threshold` 8)",
         f"recalibrated from under the line: {n_screen}, right {sum(r for _, r, _ in t.screened)},"
         f" accepted {sum(a for _, _, a in t.screened)}",
         "; ".join(c for c, r, a in t.screened if r or a) or "-"),
        ("weak lead (`weak_lead` 50: every screened candidate recalibrated)",
         f"cases whose best score test was under it: {len(t.weak)}", ", ".join(t.weak) or "-"),
    ]
    out = [f"Over {t.cases} kept cases (the window and round 1 that gave the answer):", "",
           "| line | outcome on the sweep | cases |", "|---|---|---|"]
    out += [f"| {a} | {b} | {c} |" for a, b, c in rows]
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("evidence", type=Path, nargs="+", help="folders of kept cases")
    args = ap.parse_args()
    cases = sorted(p for folder in args.evidence for p in folder.iterdir() if p.is_dir())
    print(table(tally(cases)))


if __name__ == "__main__":
    main()
