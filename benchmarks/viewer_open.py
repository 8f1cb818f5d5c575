"""How long the viewer takes to show a 100-candidate run.

Writes a run record of 100 candidates, 20 held-out views and 20 captures
(128x128 views), then, in turns, runs ``mitsuba-active view`` on it as a
user does (a fresh ``python -m mitsuba_active`` process each time), opens
the address it prints in headless Chromium (Debian's, as the tests use it)
and waits until every camera's frustum is in the page's scene. Prints the
median of each phase (start to the address printed, the page, the whole)
and writes JSON.

Usage::

    PYTHONPATH=. python benchmarks/viewer_open.py [--repeats 5] [--out benchmarks/results/viewer_open.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import re
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

#: Seconds between polls of the page: the figures' resolution.
POLL_S = 0.01

#: The line ``view`` prints once it serves: its address.
SERVING = re.compile(r"^viewing .* at (http://\S+) ")


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
            proc = subprocess.Popen([sys.executable, "-m", "mitsuba_active", "view", str(folder), "--port",
                                     str(args.port + n)], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                                    env={**os.environ, "PYTHONPATH": str(Path.cwd())})
            try:
                match = None
                while match is None:  # viser prints its own lines first
                    line = proc.stderr.readline()
                    if not line:
                        raise RuntimeError("the viewer stopped before serving")
                    match = SERVING.match(line)
                ready = time.perf_counter()
                url = match.group(1)
                browser.open(url)
                loaded = time.perf_counter()
                browser.wait_for(SCENE_TREE, interval=POLL_S)
                condition = " && ".join(f"k.{kind} === {n}" for kind, n in want.items())
                if not browser.wait_for(f"(k => {condition})({VIEWER_KINDS})", interval=POLL_S):
                    raise RuntimeError(f"the page did not show every camera: {browser.evaluate(VIEWER_KINDS)}")
                shown = time.perf_counter()
                kinds = browser.evaluate(VIEWER_KINDS)
            finally:
                proc.send_signal(signal.SIGINT)  # Ctrl-C, as a user stops it
                proc.wait(timeout=30)
            assert kinds == want, kinds
            row = {"serving_s": ready - t0, "load_s": loaded - ready, "page_s": shown - ready,
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
