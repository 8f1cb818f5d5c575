"""Export a run's chosen views as a transforms.json dataset (nerfstudio / instant-ngp).

Poses are converted to the OpenGL/Blender camera convention (camera looks
along -Z, +Y up) that those tools expect. Each frame carries its PNG image
and an EXR with the distance from the optical centre (channel ``Z``), except
in runs of a dataset without depth maps, which have no distances. The
scene's bounds are written as ``aabb`` (as :mod:`.datasets` reads them back).
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import shutil
import warnings
from pathlib import Path

from .cameras import Camera
from .datasets import mitsuba_to_opengl
from .errors import FolderError, UserError, first_line
from .imageio_utils import atomic_write, new_entries, remove_new
from .interrupts import interrupts_deferred
from .run import read_record


#: The names of the files an export writes beside transforms.json.
_WRITTEN = re.compile(r"images/view_\d{3,}\.png|distance/view_\d{3,}\.exr")


def export_transforms(run_dir, out_dir=None) -> Path:
    """Write ``transforms.json``, ``images/`` and ``distance/`` (when the run has distances)
    for a run; returns the JSON path."""
    run_dir = Path(run_dir)
    rec_path = run_dir / "run.json"
    if not rec_path.is_file():
        raise UserError(f"{run_dir} is not a run folder (no run.json)")
    rec = read_record(rec_path)
    out = Path(out_dir) if out_dir else run_dir / "export"
    cams = [Camera.from_dict(rec["candidates"][i]) for i in rec["captured"]]
    if not cams:
        raise UserError(f"{run_dir} has no captured views to export")
    if not rec["finished"]:
        budget = rec["config"].get("budget", "?")
        warnings.warn(f"{run_dir} is an unfinished run: exporting the {len(cams)} of {budget} views captured so far",
                      stacklevel=2)
    # A run of a dataset without depth maps has no distances to export.
    distances = rec.get("distances", True)
    suffixes = (".png", ".exr") if distances else (".png",)
    missing = [n for n in range(len(cams))
               if not all((run_dir / "views" / f"view_{n:03d}{suffix}").is_file() for suffix in suffixes)]
    if missing:
        raise UserError(f"{run_dir}/views is missing images{' or distance maps' if distances else ''} "
                        f"for views {missing}")
    _check_views(run_dir / "views", cams, distances)
    earlier = _earlier_export(out)
    ref = cams[0]
    # Cameras of their own (rig xml) may differ in field of view: then every
    # frame carries its intrinsics, which nerfstudio reads before the top level's.
    per_frame = any(cam.fov != ref.fov for cam in cams)
    frames = []
    # Every file goes to a temporary name first and all are renamed at the end, with
    # Ctrl-C held back: a failed export (a full disk) leaves the earlier one whole.
    top, before = new_entries(out)
    try:
        with contextlib.ExitStack() as staged:
            def stage(name: str) -> Path:
                return staged.enter_context(atomic_write(out / name))

            for n, (cam, index) in enumerate(zip(cams, rec["captured"])):
                img, dist = f"images/view_{n:03d}.png", f"distance/view_{n:03d}.exr"
                shutil.copyfile(run_dir / "views" / f"view_{n:03d}.png", stage(img))
                frame = {"file_path": img}
                if distances:
                    shutil.copyfile(run_dir / "views" / f"view_{n:03d}.exr", stage(dist))
                    frame["distance_file_path"] = dist
                if per_frame:
                    kc = cam.intrinsics()
                    frame.update(camera_angle_x=math.radians(cam.fov), fl_x=kc[0, 0], fl_y=kc[1, 1], cx=kc[0, 2],
                                 cy=kc[1, 2])
                frame["candidate"] = int(index)
                if rec.get("candidate_files"):  # a dataset's run: the frame of the dataset this view is
                    frame["source_file_path"] = rec["candidate_files"][index]
                frames.append({**frame, "transform_matrix": mitsuba_to_opengl(cam.to_world).tolist()})
            path = out / "transforms.json"
            stage("transforms.json").write_text(json.dumps(_transforms(rec, ref, distances, frames), indent=1))
            renames = staged.pop_all()
        with interrupts_deferred():
            renames.close()
    except BaseException:
        remove_new(out, top, before)  # folders a first export made
        raise
    # An export over an earlier one: its frames that this one does not have go.
    now = {f[key] for f in frames for key in ("file_path", "distance_file_path") if key in f}
    for name in sorted(earlier - now):
        (out / name).unlink(missing_ok=True)
    return path


def _transforms(rec: dict, ref: Camera, distances: bool, frames: list) -> dict:
    """The content of transforms.json: the shared camera (``ref``'s), the scene's bounds, the frames."""
    k = ref.intrinsics()
    data = {"camera_model": "OPENCV", "camera_angle_x": math.radians(ref.fov),
            "fl_x": k[0, 0], "fl_y": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "w": ref.width, "h": ref.height,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0}
    if rec.get("bbox"):  # the scene's bounds (runs recorded before they were kept have none)
        data["aabb"] = rec["bbox"]
    if distances:
        data["distance_note"] = ("distance_file_path: EXR channel Z, distance from the optical centre in scene "
                                 "units along each pixel-centre ray (not depth); 0 where nothing is hit")
    data["frames"] = frames
    return data


def _check_views(views_dir: Path, cams: list[Camera], distances: bool) -> None:
    """UserError unless every captured view's image (and distance map) reads
    as an image of its camera's size: a damaged file is refused, not copied."""
    import imageio.v3 as iio

    from .imageio_utils import read_exr

    for n, cam in enumerate(cams):
        files = [(views_dir / f"view_{n:03d}.png", lambda p: iio.imread(p, plugin="pillow").shape[:2])]
        if distances:
            files.append((views_dir / f"view_{n:03d}.exr", lambda p: read_exr(p)["Z"].shape))
        for path, size_of in files:
            try:
                size = size_of(path)
            except Exception as exc:  # noqa: BLE001 (image readers raise many kinds)
                raise UserError(f"{path} is damaged (it does not read as an image: {first_line(exc)})") from None
            if tuple(size) != (cam.height, cam.width):
                raise UserError(f"{path} is damaged: {size[1]}x{size[0]} pixels where its camera has "
                                f"{cam.width}x{cam.height}")


def _earlier_export(out: Path) -> set[str]:
    """The image and distance files an earlier export into ``out`` listed (only names that
    this module writes, so no other file is ever removed). UserError when ``out`` holds a
    dataset that no export wrote (a ``transforms*.json`` that is not an earlier export's):
    the export would replace or shadow it."""
    earlier = set()
    for path in sorted(out.glob("transforms*.json")) if out.is_dir() else []:
        frames = _exported_frames(path) if path.name == "transforms.json" else None
        if frames is None:
            raise FolderError(out, f"holds a dataset that is not an earlier export ({path.name}); "
                                   "export into another folder")
        names = {f.get(key) for f in frames for key in ("file_path", "distance_file_path")}
        earlier = {n for n in names if isinstance(n, str) and _WRITTEN.fullmatch(n)}
    return earlier


def _exported_frames(path: Path) -> list[dict] | None:
    """The frames of ``path`` when it reads as a transforms.json this module wrote (every
    frame names its candidate and an image by the name an export gives it), else None."""
    try:
        frames = json.loads(path.read_text()).get("frames")
    except (OSError, ValueError, AttributeError, RecursionError):
        return None
    ours = bool(frames) and isinstance(frames, list) and all(
        isinstance(f, dict) and "candidate" in f and isinstance(f.get("file_path"), str)
        and _WRITTEN.fullmatch(f["file_path"]) for f in frames)
    return frames if ours else None

