"""How long the viewer takes to show a 100-candidate run.

Writes a run record of 100 candidates, 20 held-out views and 20 captures
(128x128 views), then, in turns with a fresh Python process each time:
imports the viewer and starts its server (``RunViewer``), opens the page in
headless Chromium (Debian's, as the tests use it) and waits until every
camera's frustum is in the page's scene. Prints the median of each phase
and writes JSON.

Usage::

    PYTHONPATH=. python benchmarks/viewer_open.py [--repeats 5] [--out benchmarks/results/viewer_open.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import imageio.v3 as iio  # noqa: E402
import numpy as np  # noqa: E402

from mitsuba_active.rigs import fibonacci_sphere  # noqa: E402
from tests.browser import Browser  # noqa: E402
from tests.test_report import SCENE_TREE, VIEWER_KINDS  # noqa: E402

#: Serves the run, prints the seconds the imports and the server took, then waits to be stopped.
SERVE = """import sys, time
t0 = time.perf_counter()
from mitsuba_active.viewer import RunViewer
t1 = time.perf_counter()
viewer = RunViewer(sys.argv[1], port=int(sys.argv[2]))
t2 = time.perf_counter()
print(f"READY {t1 - t0} {t2 - t1} {viewer.port}", flush=True)
sys.stdin.read()
viewer.close()
"""


def write_run(folder: Path) -> dict:
    cams = fibonacci_sphere(120, (0, 0, 0), 2.0, width=128, height=128)
    rng = np.random.default_rng(0)
    captured = list(range(0, 100, 5))
    rounds = [{"views": n + 1, "picks": [captured[n]], "scores": rng.uniform(size=100).tolist()}
              for n in range(2, 20)]
    rec = {"config": {"budget": 20, "initial_views": 2, "planner": "rfe"},
           "candidates": [c.to_dict() for c in cams[:100]], "heldout": [c.to_dict() for c in cams[100:]],
           "captured": captured, "rounds": rounds, "bbox": [[-0.5] * 3, [0.5] * 3],
           "metrics": [{"views": 20, "psnr": 20.5, "ssim": None, "distance_error": None}], "finished": True}
    (folder / "views").mkdir(parents=True, exist_ok=True)
    for n in range(20):
        iio.imwrite(folder / "views" / f"view_{n:03d}.png", rng.integers(0, 256, (128, 128, 3), dtype=np.uint8))
    (folder / "run.json").write_text(json.dumps(rec))
    return rec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--port", type=int, default=8765)
    ap.add_argument("--out", default="benchmarks/results/viewer_open.json")
    args = ap.parse_args(argv)
    want = {"candidates": 100, "heldout": 20, "captured": 20}
    rows = []
    with tempfile.TemporaryDirectory() as tmp, Browser(timeout=60.0) as browser:
        folder = Path(tmp) / "run"
        write_run(folder)
        for n in range(args.repeats):
            t0 = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-c", SERVE, str(folder), str(args.port + n)],
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                    env={**__import__("os").environ, "PYTHONPATH": str(Path.cwd())})
            try:
                line = ""
                while not line.startswith("READY"):  # viser prints its own lines first
                    line = proc.stdout.readline()
                    if not line:
                        raise RuntimeError("the viewer stopped before serving")
                imports, server, port = line.split()[1:]
                ready = time.perf_counter()
                browser.open(f"http://127.0.0.1:{port}")
                browser.wait_for(SCENE_TREE)
                condition = " && ".join(f"k.{kind} === {n}" for kind, n in want.items())
                if not browser.wait_for(f"(k => {condition})({VIEWER_KINDS})"):
                    raise RuntimeError(f"the page did not show every camera: {browser.evaluate(VIEWER_KINDS)}")
                shown = time.perf_counter()
                kinds = browser.evaluate(VIEWER_KINDS)
            finally:
                proc.stdin.close()
                proc.wait(timeout=30)
            assert kinds == want, kinds
            row = {"imports_s": float(imports), "server_s": float(server), "page_s": shown - ready,
                   "total_s": shown - t0}
            rows.append(row)
            print(" ".join(f"{k} {v:.2f}" for k, v in row.items()), flush=True)
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
    print("median: " + " ".join(f"{k} {v:.2f}" for k, v in med.items()))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"runs": rows, "median": med, "machine": platform.machine()}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
