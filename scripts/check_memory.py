"""Check `ptrack.pipeline.memory.estimate_bytes` against the peak resident memory of real runs.

Each setting runs `ptrack.pipeline.run.execute` in a fresh subprocess (into a temporary folder); its peak RSS
(its own getrusage ru_maxrss at the end) is compared with the estimate for the same config and clip. The
estimate should stay above the measurement (ratio >= 1) and within a few times it.

    python scripts/check_memory.py                 # every setting below (a few minutes on 2 cores)
    python scripts/check_memory.py --only kjs      # the settings whose label starts with kjs
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SETTINGS = [
    ("frame", "configs/kjs.yaml", ["method=frame", "data.stop=60"]),
    ("kjs", "configs/kjs.yaml", ["data.stop=60"]),
    ("kjs samples=2048", "configs/kjs.yaml", ["data.stop=20", "kjs.samples=2048"]),
    ("kjs modes=64", "configs/kjs.yaml", ["data.stop=20", "kjs.modes=64", "kjs.samples=512"]),
    ("kjs init=tree", "configs/kjs.yaml", ["data.stop=20", "kjs.init=tree"]),
    ("css samples=2048", "configs/kjs.yaml", ["method=css", "data.stop=20", "kjs.samples=2048"]),
    ("batch", "configs/batch.yaml", ["data.stop=60"]),
    ("batch 300 frames", "configs/batch.yaml", ["data.stride=1", "data.stop=300", "batch.iterations=5"]),
    ("pca", "configs/golf.yaml", []),  # the whole swing: its key postures set the initial timing
    ("pca init_yaws=256", "configs/golf.yaml", ["pca.init_yaws=256"]),
]

CHILD = """
import dataclasses, resource, sys
import ptrack.pipeline.run
from ptrack.pipeline.config import load_config
from ptrack.pipeline.memory import needed

need = []
ptrack.pipeline.run.check_memory = lambda cfg, problem: need.append(needed(cfg, problem).bytes)
cfg = load_config(sys.argv[1], sys.argv[3:])
ptrack.pipeline.run.execute(dataclasses.replace(cfg, out_dir=sys.argv[2], progress=False))
print(need[0] / 2**20, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)  # MiB (ru_maxrss: KiB on Linux)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="run the settings whose label starts with this")
    args = ap.parse_args()
    for label, config, overrides in SETTINGS:
        if not label.startswith(args.only):
            continue
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.time()
            out = subprocess.run(
                [sys.executable, "-c", CHILD, str(ROOT / config), str(Path(tmp) / "run"), *overrides],
                capture_output=True,
                text=True,
            )
            seconds = time.time() - t0
        if out.returncode != 0:
            print(f"{label:24s} failed: {(out.stderr.strip().splitlines() or ['?'])[-1]}", flush=True)
            continue
        need, peak = (float(x) for x in out.stdout.split()[-2:])
        print(
            f"{label:24s} measured {peak:7.0f} MiB  estimate {need:7.0f} MiB  ratio {need / peak:5.2f}"
            f"  ({seconds:.0f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
