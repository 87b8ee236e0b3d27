"""The answer by the evidence on real OPM runs of the small synthetic case (issue 46): hide an
effect on the small deck (the built-in true globals), diagnose it from the true globals with
the cheap settings of tests/test_diagnosis_hidden.py's flow test, and print the weighed
explanations, the answer and how the judge counts it. The table of docs/diagnosis.md ("The
answer: explanations weighed by their evidence") was made with

    python benchmarks/diagnosis_answer_small.py well_skin 1 2 regional_permeability 1 2 3 control 1

(pairs of a kind, or ``control``, and its seeds; ``--kinds`` the families searched, default
``well_skin,regional_permeability``; ``--root`` the work folder).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from hmcore.cases import load_case
from hmcore.diagnosis import DiagnosisSettings, diagnose
from hmcore.diagnosis.runs import local_evaluator
from hmcore.scenarios.effects import load_hidden_effects
from hmcore.scenarios.hide import hide_case
from hmcore.scenarios.judge import judge_effects
from hmcore.scenarios.synthetic import SYNTHETIC_TRUTH, write_synthetic_case
from hmcore.scenarios.synthetic_deck import SMALL_LAYOUT

CHEAP = {"confirm_top": 2, "confirm_max": 2, "confirm_weak_max": 2, "near_bound": -1.0,
         "restart_on_veto": False, "max_causes": 1}
"""tests/test_diagnosis_hidden.py's FLOW_SETTINGS."""


def one(root: Path, kind: str, seed: int, kinds: tuple[str, ...]) -> dict:
    """Hide, diagnose and judge one case; returns the row printed."""
    shutil.rmtree(root, ignore_errors=True)
    small = write_synthetic_case(root / "small", 0, layout=SMALL_LAYOUT)
    h = hide_case(root / "case", seed=seed, kind=None if kind == "control" else kind,
                  deck=small.parent / "SYNTH.DATA", globals_=dict(SYNTHETIC_TRUTH))
    settings = DiagnosisSettings(plots=False, kinds=kinds, **CHEAP)
    t0 = time.perf_counter()
    doc = diagnose(load_case(h.case_toml), local_evaluator(root / "runs", workers=2),
                   calibrated=dict(SYNTHETIC_TRUTH), settings=settings, out_dir=root / "out")
    effects = load_hidden_effects(h.hidden_json)
    j = judge_effects(doc, list(effects), json.loads(h.hidden_json.read_text()).get("signal"))
    return {"hidden": [e.candidate.id for e in effects], "seed": seed,
            "selected": (doc["selected"] or {}).get("id"), "found": j["found"],
            "outcome": j["outcome"], "set_size": j["set_size"],
            "weights": {x["id"]: round(x["weight"], 3) for x in doc["answer"]["explanations"]},
            "answer": doc["answer"]["text"], "simulations": doc["cost"]["simulations"],
            "wall_s": round(time.perf_counter() - t0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", help="a kind (or control) followed by its seeds, ...")
    ap.add_argument("--kinds", default="well_skin,regional_permeability")
    ap.add_argument("--root", type=Path, default=Path("diagnosis-answer-small"))
    args = ap.parse_args()
    kind, kinds = None, tuple(args.kinds.split(","))
    for token in args.cases:
        if not token.isdigit():
            kind = token
            continue
        row = one(args.root / f"{kind}-{token}", kind, int(token), kinds)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
