"""Rendered views in a folder: a scene's ground truth at chosen cameras, as EXR and PNG files and cameras.json."""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
from pathlib import Path

from tqdm import tqdm

from .imageio_utils import colorize, new_entries, remove_new, srgb_to_linear, write_exr, write_png
from .interrupts import interrupts_deferred

#: The files ``render`` writes for a view: its EXR, its PNG and the PNG of its distances.
RENDERED = re.compile(r"(cand|held)_\d{3,}(\.exr|\.png|_distance\.png)")


def rendered_files(cameras_json: Path) -> set[str]:
    """The files of the render that wrote ``cameras_json`` (only names that ``render`` writes,
    so no other file is ever removed); none if there is no such render."""
    try:
        views = json.loads(cameras_json.read_text()).get("views", [])
        stems = {Path(v["file"]).stem for v in views}
    except (OSError, ValueError, AttributeError, KeyError, TypeError, RecursionError):
        return set()
    names = {stem + end for stem in stems if isinstance(stem, str) for end in (".exr", ".png", "_distance.png")}
    return {n for n in names if RENDERED.fullmatch(n)}


def render_views(source, cams: list, split: str, out, progress: bool = True) -> None:
    """Render the cameras ``cams`` of a scene source into the folder ``out``:
    for view i of ``split`` (``candidates`` or ``heldout``), ``cand_iii.exr``
    or ``held_iii.exr`` (linear RGB, and the distance in Z), a PNG and a PNG
    of its distances, and ``cameras.json`` listing them with their cameras.

    The views replace an earlier render in ``out`` whole, or not at all: an
    interrupted render leaves it as it was.
    """
    out = Path(out)
    new = new_entries(out)
    # Views are rendered into a hidden folder and moved in at the end, so that
    # an interrupted render leaves an earlier render in OUT as it was.
    stage = out / f".render-{secrets.token_hex(6)}"
    records = []
    try:
        stage.mkdir(parents=True)
        for i, cam in enumerate(tqdm(cams, desc="rendering", unit="view", disable=not progress)):
            v = source.groundtruth.render(cam)
            stem = f"{split[:4]}_{i:03d}"
            write_exr(stage / f"{stem}.exr", {"RGB": srgb_to_linear(v.rgb), "Z": v.distance})
            write_png(stage / f"{stem}.png", v.rgb)
            write_png(stage / f"{stem}_distance.png", colorize(v.distance, v.mask))
            records.append({"file": f"{stem}.png", **cam.to_dict(), "intrinsics": cam.intrinsics().tolist()})
        (stage / "cameras.json").write_text(json.dumps({"scene": str(source.scene.path), "split": split,
                                                        "views": records}, indent=1))
        earlier = rendered_files(out / "cameras.json")
        written = {p.name for p in stage.iterdir()} - {"cameras.json"}
        with interrupts_deferred():  # the views, their cameras.json, then the earlier render's other views
            for name in sorted(written):
                os.replace(stage / name, out / name)
            os.replace(stage / "cameras.json", out / "cameras.json")
            for name in sorted(earlier - written):
                (out / name).unlink(missing_ok=True)
    except BaseException:
        remove_new(out, *new)  # views without their cameras.json are no use to anyone
        raise
    finally:
        shutil.rmtree(stage, ignore_errors=True)
