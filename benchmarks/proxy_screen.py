"""Screen calibration-method variants on a surrogate of a real misfit landscape, in seconds.

    python benchmarks/proxy_screen.py --journals DIR [--case synthetic] [--methods sac,cmaes]
                                      [--seeds 5] [--budget 100] [--workers 2]
                                      [--sac '{"candidates": 0}']

The surrogate: log E interpolated (scipy RBFInterpolator, thin-plate spline, smoothed) over every
journaled call of a benchmark (``DIR``: the extracted ``journals.tar.gz`` of
``benchmarks/results/<bench>/``), plus the case's real physics penalty (``check_physics``: it
needs no simulation). A screen, not a result: what a variant gains here must be confirmed by
``hmflow bench`` on the real simulator (the README's figures are never from this script).
Methods that need the residual vector (lm, esmda) cannot run on it.
"""

from __future__ import annotations

import argparse
import glob
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def load_points(journals: Path) -> tuple[np.ndarray, np.ndarray]:
    X, E = [], []
    for f in glob.glob(str(journals / "*" / "evaluations" / "*.json")):
        r = json.loads(Path(f).read_text())
        if r.get("action") is not None and r.get("E") is not None:
            X.append(r["action"])
            E.append(r["E"])
    return np.array(X, float), np.array(E, float)


class Surrogate:
    def __init__(self, X: np.ndarray, E: np.ndarray, case):
        from scipy.interpolate import RBFInterpolator

        from hmcore.model.case import PhysicsSettings

        self.rbf = RBFInterpolator(X, np.log(E), kernel="thin_plate_spline", smoothing=1e-3,
                                   neighbors=200)
        self.case = case
        self.physics = getattr(case, "physics", None) or PhysicsSettings()

    def record(self, job) -> dict:
        from hmcore.scoring.physics import check_physics

        E = float(np.exp(self.rbf(np.asarray(job.action, float)[None])[0]))
        check = check_physics(job.values, self.case.space, self.case.info, self.physics)
        penalty = float(check.penalty)
        return {"index": job.index, "action": list(job.action), "params": job.values,
                "E": E, "penalty": penalty, "reward": -E - penalty,
                "status": "COMPLETE" if check.valid else "INVALID"}


def run(method: str, seed: int, budget: int, workers: int, surrogate: Surrogate,
        sac: dict) -> np.ndarray:
    from hmcore.calibration.methods import make_proposer
    from hmcore.calibration.loop import calibrate

    proposer = make_proposer(method, surrogate.case.space.dim, seed, workers, budget,
                             **(sac if method == "sac" else {}))
    records = calibrate(proposer, surrogate.case.space,
                        lambda jobs: [surrogate.record(j) for j in jobs], budget, workers)
    E = np.array([r["E"] if r["status"] == "COMPLETE" else np.inf for r in records])
    return np.minimum.accumulate(E)


def main() -> None:
    from hmcore.cases import load_case, resolve_case_path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--journals", type=Path, required=True)
    ap.add_argument("--case", default="synthetic")
    ap.add_argument("--floor", type=float, default=None, help="default: the lowest E journaled")
    ap.add_argument("--methods", default="sac,cmaes,de,bo,sobol,random")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--budget", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sac", default="{}", help="SAC settings as JSON")
    args = ap.parse_args()
    case = load_case(resolve_case_path(args.case))
    X, E = load_points(args.journals)
    surrogate = Surrogate(X, E, case)
    floor = args.floor or float(E.min())
    print(f"{len(E)} journaled points; floor {floor:.6g}")
    for method in args.methods.split(","):
        hits = {lv: [] for lv in (1.5, 1.2, 1.1)}
        finals = []
        for seed in range(args.seeds):
            best = run(method, seed, args.budget, args.workers, surrogate, json.loads(args.sac))
            finals.append(best[-1] / floor)
            for lv in hits:
                k = np.flatnonzero(best <= lv * floor)
                hits[lv].append(k[0] + 1 if k.size else np.inf)
        text = "  ".join(f"{lv}x: {np.median(h):.0f} ({np.isfinite(h).sum()}/{len(h)})"
                         for lv, h in hits.items())
        print(f"{method:8s} {text}  final {np.median(finals):.3f}x")


if __name__ == "__main__":
    main()
