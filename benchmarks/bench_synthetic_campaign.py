"""Does a campaign on the synthetic case reach the noise floor, and how close to the truth?

    python benchmarks/bench_synthetic_campaign.py --storage ./hmflow-storage --campaign synthetic-sac-seed0
    python benchmarks/bench_synthetic_campaign.py --run --budget 200     # run the campaign first

The noise band of E: the noise-free truth responses are scored against K fresh noise
realisations of the observed history (same noise model as the case, other seeds), giving the
spread of E that noise alone produces at the true parameters. A found E is "within the noise of
the truth's E" when E_found <= E_truth + 2 * std(E_noise). No simulator time is needed for the
band (the truth responses ship with the case as truth_responses.csv).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def noise_band(case, truth: pd.DataFrame, k: int, seed: int) -> np.ndarray:
    from hmcore.model.case import Case
    from hmcore.scoring.evaluation import score_responses
    from hmcore.model.observed import derive_phase_rates
    from hmcore.scenarios.synthetic import make_observed

    out = []
    for rng in np.random.default_rng(seed).spawn(k):
        obs, _ = make_observed(truth, rng)
        obs = obs.assign(flowing=obs["flowing"].astype(bool), derived=False, line=-1)
        obs = derive_phase_rates(obs[["well", "days", "quantity", "value", "sigma", "flowing",
                                      "derived", "line"]])
        noisy = Case(**{**case.__dict__, "observed": obs})
        out.append(score_responses(noisy, truth)["E"])
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--storage", type=Path, default=Path("hmflow-storage"))
    ap.add_argument("--campaign", default="synthetic-sac-seed0")
    ap.add_argument("--run", action="store_true", help="run `hmflow run` first")
    ap.add_argument("--agent", default="sac", help="the method of the campaign --run makes "
                    "(default sac, as the lab notes measured; the campaign name says it)")
    ap.add_argument("--budget", type=int, default=200)
    ap.add_argument("--k", type=int, default=30, help="noise realisations for the band")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from hmcore.cases import load_case
    from hmcore.scoring.evaluation import score_responses
    from hmcore.scenarios.synthetic import ensure_synthetic_case
    from storage import ArtifactStore

    if args.run:
        subprocess.run([sys.executable, "-m", "hmflow.cli", "run", "--budget", str(args.budget),
                        "--agent", args.agent, "--storage", str(args.storage), "--campaign",
                        args.campaign], check=True,
                       timeout=24 * 3600)
    case_toml = ensure_synthetic_case()
    case = load_case(case_toml)
    truth_resp = pd.read_csv(case_toml.parent / "truth_responses.csv")
    truth_params = json.loads((case_toml.parent / "truth.json").read_text())["parameters"]
    e_truth = score_responses(case, truth_resp)["E"]
    band = noise_band(case, truth_resp, args.k, seed=12345)
    store = ArtifactStore(args.storage)
    best = store.latest(args.campaign, "best").read_json("metrics.json")
    table = store.latest(args.campaign, "results").read_parquet("evaluations.parquet")
    limit = e_truth + 2 * band.std()
    result = {
        "E_truth": e_truth, "E_noise_mean": float(band.mean()), "E_noise_std": float(band.std()),
        "E_found": best["E"], "within_noise": bool(best["E"] <= limit), "limit": limit,
        "calls": len(table), "best_index": best["index"],
        "params": {k: {"found": best["params"][k], "truth": truth_params[k]} for k in truth_params},
        "E_heldout_found": best.get("E_heldout"),
    }
    print(json.dumps(result, indent=2))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
