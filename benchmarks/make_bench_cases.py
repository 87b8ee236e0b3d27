"""Benchmark cases whose truth lies elsewhere in the box: PUNQ-S3 (or any deck) histories made
from moved global parameters, so that no method wins by starting at the deck's own values.

    python benchmarks/make_bench_cases.py --out DIR [--deck ../shared/punqs3/PUNQS3.DATA]
                                          [--seeds 1 2 3] [--record-end 2936]

For each seed: the five reference globals are drawn uniformly in the paper's box
(``numpy.random.default_rng([seed, 17])``), redrawn until no physics check fires (the truth is
a physical model); the deck is run with them (OPM Flow), the benchmark's correlated noise is
added (``hmflow hide``'s noise model) and ``DIR/punq-moved-<seed>/case.toml`` is written with
the whole record fitted. The truth is in ``hidden_effect.json`` (``truth``), where ``hmflow
bench`` finds it for the floor. The deck is read in place, never copied.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def draw_valid_truth(seed: int, deck: Path, stream: int = 17) -> dict[str, float]:
    """The five globals drawn uniformly in the box (``default_rng([seed, stream])``) until no
    physics check of ``deck`` fires."""
    from hmcore.model.case import PhysicsSettings
    from hmcore.eclipse.deck_info import DeckInfo
    from hmcore.model.parameters import ParameterSpace
    from hmcore.scoring.physics import check_physics

    space, info = ParameterSpace.reference(), DeckInfo.inspect(deck)
    rng = np.random.default_rng([seed, stream])
    for _ in range(1000):
        values = space.to_values(rng.uniform(-1.0, 1.0, space.dim))
        if check_physics(values, space, info, PhysicsSettings()).valid:
            return {k: round(v, 4) for k, v in values.items()}
    raise RuntimeError(f"no physically valid truth in 1000 draws for seed {seed}")


def main() -> None:
    from hmcore.scenarios.hidden import write_hidden_deck_case

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--deck", type=Path, default=REPO.parent / "shared/punqs3/PUNQS3.DATA")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--record-end", type=float, default=2936.0)
    args = ap.parse_args()
    for seed in args.seeds:
        dest = args.out / f"punq-moved-{seed}"
        if dest.exists():
            print(f"{dest} exists: kept as it is")
            continue
        truth = draw_valid_truth(seed, args.deck.resolve())
        case, _ = write_hidden_deck_case(dest, args.deck, seed, truth=truth,
                                         history_end_days=args.record_end,
                                         end_days=args.record_end, with_sigma=False,
                                         name=dest.name)
        print(f"{case}: truth {json.dumps(truth)}")


if __name__ == "__main__":
    main()
