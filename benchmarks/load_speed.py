"""How long a phone-sized capture takes to load: 100 JPEGs of 1080x1920 at downscale 8.

Writes a transforms.json capture of ``--frames`` JPEG frames (``--width`` x
``--height``, portrait by default, as phones take them; smooth colour
fields with fine grain, so that they compress as photographs do), then, in
turns, times in a fresh Python process each: opening the dataset at
``--downscale`` and reading every frame's view (``DatasetSource.from_path``,
then ``candidate_view`` and ``heldout_view`` for all), with an empty cache
(``cold``) and with the cache that the cold load filled (``warm``). Prints
the medians and writes JSON.

Usage::

    PYTHONPATH=. python benchmarks/load_speed.py [--frames 100] [--repeats 3]
        [--out benchmarks/results/load_speed.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np

#: Loads the dataset in a fresh process and prints its seconds and the views' size.
LOAD = """import sys, time
t0 = time.perf_counter()
import mitsuba_active
from mitsuba_active.datasets import DatasetSource
t1 = time.perf_counter()
src = DatasetSource.from_path(sys.argv[1], downscale=int(sys.argv[2]), cache_dir=sys.argv[3])
views = [src.candidate_view(i) for i in range(len(src.candidates))]
views += [src.heldout_view(i) for i in range(len(src.heldout))]
t2 = time.perf_counter()
print("LOADED", t1 - t0, t2 - t1, len(views), views[0].rgb.shape[1], views[0].rgb.shape[0], flush=True)
"""


def write_capture(root: Path, frames: int, width: int, height: int, seed: int = 0) -> Path:
    """``frames`` JPEGs on a circle around the origin, every 10th a test frame; returns the transforms.json."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    entries = []
    for k in range(frames):
        f = rng.uniform(2, 6, 3)
        p = rng.uniform(0, 2 * np.pi, 3)
        img = np.stack([0.5 + 0.4 * np.sin(f[c] * xx / width * 2 * np.pi + p[c]) * np.cos(f[c] * yy / height * np.pi)
                        for c in range(3)], axis=-1)
        img = img + rng.normal(0, 0.03, img.shape).astype(np.float32)
        name = f"images/frame_{k:04d}.jpg"
        iio.imwrite(root / name, (np.clip(img, 0, 1) * 255).astype(np.uint8), quality=90)
        a = 2 * np.pi * k / frames
        pos = np.array([3 * math.cos(a), 0.5, 3 * math.sin(a)])
        fwd = -pos / np.linalg.norm(pos)  # OpenGL camera: looks down -z
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, -fwd, pos
        entries.append({"file_path": name, "transform_matrix": m.tolist(),
                        "split": "test" if k % 10 == 9 else "train"})
    meta = {"camera_angle_x": math.radians(60.0), "w": width, "h": height, "aabb": [[-1, -1, -1], [1, 1, 1]],
            "frames": entries}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root / "transforms.json"


def load_once(path: Path, downscale: int, cache: Path) -> dict:
    """One load in a fresh process: imports, then the dataset and every view."""
    proc = subprocess.run([sys.executable, "-c", LOAD, str(path), str(downscale), str(cache)], capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("LOADED")), None)
    if proc.returncode or line is None:
        raise RuntimeError(f"the load failed: {proc.stderr.strip().splitlines()[-1:]}")
    imports, load, n, w, h = line.split()[1:]
    return {"imports_s": float(imports), "load_s": float(load), "views": int(n), "size": [int(w), int(h)]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=1080)
    ap.add_argument("--height", type=int, default=1920)
    ap.add_argument("--downscale", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/load_speed.json")
    args = ap.parse_args(argv)
    if min(args.frames, args.width, args.height, args.downscale, args.repeats) < 1:
        ap.error("--frames, --width, --height, --downscale and --repeats must be at least 1")
    rows = {"cold": [], "warm": []}
    with tempfile.TemporaryDirectory() as tmp:
        path = write_capture(Path(tmp) / "capture", args.frames, args.width, args.height)
        cache = Path(tmp) / "cache"
        for n in range(args.repeats):  # in turns: a cold load, then a warm one from the cache it filled
            shutil.rmtree(cache, ignore_errors=True)
            for kind in ("cold", "warm"):
                row = load_once(path, args.downscale, cache)
                rows[kind].append(row)
                print(f"{kind}: imports {row['imports_s']:.2f} s, load {row['load_s']:.2f} s "
                      f"({row['views']} views of {row['size'][0]}x{row['size'][1]})", flush=True)
    med = {kind: {k: statistics.median(r[k] for r in rs) for k in ("imports_s", "load_s")} for kind, rs in rows.items()}
    print(f"median load of {args.frames} frames of {args.width}x{args.height} at downscale {args.downscale}: "
          f"cold {med['cold']['load_s']:.2f} s, warm {med['warm']['load_s']:.2f} s (imports apart: "
          f"{med['cold']['imports_s']:.2f} s)")
    out = {"frames": args.frames, "width": args.width, "height": args.height, "downscale": args.downscale,
           "runs": rows, "median": med, "machine": platform.machine(), "cpus": os.cpu_count()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
