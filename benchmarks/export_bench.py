"""Copy a benchmark's latest table and its campaigns' journals into the repository.

    python benchmarks/export_bench.py --name bench-punqs3 [--storage hmflow-storage]
                                      [--out benchmarks/results]

Writes ``OUT/<name>/``: the files of the latest ``<name>/benchmark/vNNNN`` (summary.md,
summary.parquet, runs.parquet, calls.parquet, best_so_far.png, references.json) and
``journals.tar.gz``: ``campaign.json`` and every ``evaluations/*.json`` of the benchmark, its
reference campaign and every campaign of the table (without the residual vectors of older
records: large, and rebuilt by rescoring; with the simulated rows of newer ones, which the
likelihood is scored from), each campaign's noise refinements (``noise/``: the likelihood of
its calls is under the last), and the case artifact the benchmark is bound to (its reference
campaign's ``case/vNNNN``, which a resumed benchmark compares the case with). Unpacked into a
store (``tar -xzf ... -C hmflow-storage``), the same ``hmflow bench`` command continues the
benchmark on another machine.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import sys
import tarfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main() -> None:
    from storage import ArtifactStore

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--name", required=True)
    ap.add_argument("--storage", type=Path, default=Path("hmflow-storage"))
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = ap.parse_args()
    store = ArtifactStore(args.storage)
    version = store.latest(args.name, "benchmark")
    if version is None:
        raise SystemExit(f"no benchmark {args.name!r} in {args.storage}: run hmflow bench first")
    dest = args.out / args.name
    dest.mkdir(parents=True, exist_ok=True)
    for name in version.files:
        shutil.copy2(version.file(name), dest / name)
    manifest = json.loads((version.path / "manifest.json").read_text())
    campaigns = [args.name, manifest["inputs"]["reference"], *manifest["inputs"]["campaigns"]]
    with tarfile.open(dest / "journals.tar.gz", "w:gz") as tar:
        for campaign in campaigns:
            root = args.storage / campaign
            files = [root / "campaign.json", *sorted((root / "evaluations").glob("*.json"))]
            for f in files:
                if not f.is_file():
                    continue
                data = json.loads(f.read_text())
                data.pop("residuals", None)
                blob = (json.dumps(data, sort_keys=True) + "\n").encode()
                info = tarfile.TarInfo(f"{campaign}/{f.relative_to(root)}")
                info.size = len(blob)
                info.mtime = int(f.stat().st_mtime)
                tar.addfile(info, io.BytesIO(blob))
            if (root / "noise").is_dir():  # the refinements its likelihood is under
                tar.add(root / "noise", arcname=f"{campaign}/noise")
        bound = json.loads((args.storage / args.name / "campaign.json").read_text())
        ref = bound["case_artifact"]
        case_dir = args.storage / ref["campaign"] / ref["step"] / f"v{int(ref['version']):04d}"
        if not case_dir.is_dir():
            raise SystemExit(f"{case_dir}: the case artifact {args.name} is bound to is missing")
        tar.add(case_dir, arcname=str(case_dir.relative_to(args.storage)))
    print(f"{dest}: {sorted(p.name for p in dest.iterdir())} from {version.path}")


if __name__ == "__main__":
    main()
