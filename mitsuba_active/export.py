"""Export a run's views as a transforms.json dataset (nerfstudio / instant-ngp).

Three files describe one split: ``transforms_train.json`` holds the run's
chosen views, ``transforms_test.json`` its held-out views, and
``transforms.json`` both, with nerfstudio's ``train_filenames`` /
``val_filenames`` / ``test_filenames`` naming the split. Poses are in the
OpenGL/Blender camera convention (camera looks along -Z, +Y up) that those
tools expect. Each frame carries its PNG image; an EXR with the distance
from the optical centre (channel ``Z``), except in runs of a dataset
without depth maps; and a mask (``mask_path``, white where the view sees
geometry) when the run knows where that is. The images are the views the
run's fields trained on and were scored against: a pinhole's (``OPENCV``,
``k1`` .. ``p2`` = 0), or a dataset camera's as captured with its lens
(``camera_model``, ``fl_x`` .. ``cy`` and coefficients at the exported
resolution); a dataset frame with a lens also keeps its source image's
lens in ``source_camera``. The scene's bounds are
written as ``aabb`` (as :mod:`.datasets` reads them back).
"""

from __future__ import annotations

import contextlib
import json
import math
import re
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .cameras import Camera
from .datasets import mitsuba_to_opengl
from .errors import FolderError, UserError, first_line
from .imageio_utils import atomic_write, new_entries, read_exr, remove_new, srgb_to_linear, write_exr, write_png
from .interrupts import interrupts_deferred
from .record import run_cameras
from .run import RunConfig, read_record

#: The names of the files an export writes beside its JSON files.
_WRITTEN = re.compile(r"(images|masks)/(view|heldout)_\d{3,}\.png|distance/(view|heldout)_\d{3,}\.exr")
#: The export's JSON files: every frame (split by file lists), the chosen views, the held-out views.
ALL_FILE, TRAIN_FILE, TEST_FILE = "transforms.json", "transforms_train.json", "transforms_test.json"
#: The frame key naming a view's index among the run's candidates, or among its held-out views.
INDEX_KEYS = ("candidate", "heldout")


@dataclass
class ExportFrame:
    """One frame of an export: where its pixels come from, and what the JSON says of it.

    Attributes:
        name: the files' stem (``view_000``, ``heldout_000``).
        camera: the view's camera.
        rgb: the run's PNG to copy, or an (H, W, 3) float32 sRGB image in [0, 1].
        distance: the run's EXR to copy, or an (H, W) float32 distance map in
            scene units (0: nothing hit), or None (the run has no distances).
        mask: (H, W) bool, True where the view sees geometry, or None (unknown).
        keys: the frame's own JSON keys (its index, its source frame).
    """

    name: str
    camera: Camera
    rgb: Path | np.ndarray
    distance: Path | np.ndarray | None
    mask: np.ndarray | None
    keys: dict = field(default_factory=dict)


def export_transforms(run_dir, out_dir=None) -> Path:
    """Write ``transforms.json``, ``transforms_train.json``, ``transforms_test.json``,
    ``images/``, ``masks/`` (when known) and ``distance/`` (when the run has distances)
    for a run; returns the path of ``transforms.json``."""
    run_dir = Path(run_dir)
    rec_path = run_dir / "run.json"
    if not rec_path.is_file():
        raise UserError(f"{run_dir} is not a run folder (no run.json)")
    rec = read_record(rec_path)
    out = Path(out_dir) if out_dir else run_dir / "export"
    cams = [Camera.from_dict(run_cameras(rec)[i]) for i in rec["captured"]]
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
    _check_views(run_dir / "views", [(f"view_{n:03d}", cam) for n, cam in enumerate(cams)], distances)
    earlier = _earlier_export(out)
    train, test = _frames(run_dir, rec, cams, distances)
    # nerfstudio reads masks for every frame or for none.
    masks = all(f.mask is not None for f in train + test)
    ref = cams[0]
    # Cameras of their own (rig xml) may differ in field of view: then every
    # frame carries its intrinsics, which nerfstudio reads before the top level's.
    per_frame = any(camera_keys(f.camera) != camera_keys(ref) for f in train + test)
    # Every file goes to a temporary name first and all are renamed at the end, with
    # Ctrl-C held back: a failed export (a full disk) leaves the earlier one whole.
    top, before = new_entries(out)
    try:
        with contextlib.ExitStack() as staged:
            def stage(name: str) -> Path:
                return staged.enter_context(atomic_write(out / name))

            entries = {}
            for frame in train + test:
                entries[frame.name] = _write_frame(frame, stage, masks, per_frame)
            train_entries = [entries[f.name] for f in train]
            test_entries = [entries[f.name] for f in test]
            split = {"train_filenames": [e["file_path"] for e in train_entries],
                     "val_filenames": [e["file_path"] for e in test_entries],
                     "test_filenames": [e["file_path"] for e in test_entries]}
            for name, frames, extra in ((ALL_FILE, train_entries + test_entries, split),
                                        (TRAIN_FILE, train_entries, {}), (TEST_FILE, test_entries, {})):
                data = _transforms(rec, ref, distances, masks, frames)
                stage(name).write_text(json.dumps({**data, **extra}, indent=1))
            renames = staged.pop_all()
        with interrupts_deferred():
            renames.close()
    except BaseException:
        remove_new(out, top, before)  # folders a first export made
        raise
    # An export over an earlier one: its frames that this one does not have go.
    now = {e[key] for e in entries.values() for key in ("file_path", "distance_file_path", "mask_path") if key in e}
    for name in sorted(earlier - now):
        (out / name).unlink(missing_ok=True)
    return out / ALL_FILE


def _write_frame(frame: ExportFrame, stage, masks: bool, per_frame: bool) -> dict:
    """Stage one frame's files; its JSON entry."""
    img, dist, mask = f"images/{frame.name}.png", f"distance/{frame.name}.exr", f"masks/{frame.name}.png"
    if isinstance(frame.rgb, Path):
        shutil.copyfile(frame.rgb, stage(img))
    else:
        write_png(stage(img), frame.rgb)
    entry = {"file_path": img}
    if isinstance(frame.distance, Path):
        shutil.copyfile(frame.distance, stage(dist))
    elif frame.distance is not None:
        write_exr(stage(dist), {"RGB": srgb_to_linear(frame.rgb), "Z": frame.distance})
    if frame.distance is not None:
        entry["distance_file_path"] = dist
    if masks:
        write_png(stage(mask), frame.mask.astype(np.float32))
        entry["mask_path"] = mask
    cam = frame.camera
    if per_frame:
        entry.update(camera_keys(cam))
    return {**entry, **frame.keys, "transform_matrix": mitsuba_to_opengl(cam.to_world).tolist()}


def _frames(run_dir: Path, rec: dict, cams: list[Camera], distances: bool):
    """``(train, test)`` lists of :class:`ExportFrame`: the chosen views from ``views/``, the held-out
    views from ``heldout/`` (a finished scene run's ground truth) or else from the run's source."""
    files = rec.get("candidate_files")  # a dataset's run: its frames are known by their files
    source = _RunSource(run_dir, rec) if files else None
    train = []
    for n, (cam, index) in enumerate(zip(cams, rec["captured"])):
        png, exr = run_dir / "views" / f"view_{n:03d}.png", run_dir / "views" / f"view_{n:03d}.exr"
        keys = {"candidate": int(index)}
        if files:
            keys.update(source.frame_keys("candidate", index))
            mask = source.mask("candidate", index)
        else:  # a scene's: its ground truth's distances say where it hits
            mask = _read_distance(exr) > 0
        train.append(ExportFrame(f"view_{n:03d}", cam, png, exr if distances else None, mask, keys))
    held = [Camera.from_dict(c) for c in rec["heldout"]]
    gt = run_dir / "heldout"
    named = [(f"heldout_{i:03d}_gt", cam) for i, cam in enumerate(held)]
    on_disk = not files and all((gt / f"{name}{s}").is_file() for name, _ in named for s in (".png", ".exr"))
    if on_disk:
        _check_views(gt, named, distances)
    elif source is None:
        source = _RunSource(run_dir, rec)
    test = []
    for i, cam in enumerate(held):
        keys = {"heldout": i}
        if on_disk:
            exr = gt / f"heldout_{i:03d}_gt.exr"
            test.append(ExportFrame(f"heldout_{i:03d}", cam, gt / f"heldout_{i:03d}_gt.png", exr,
                                    _read_distance(exr) > 0, keys))
            continue
        view = source.view("heldout", i)
        if files:
            keys.update(source.frame_keys("heldout", i))
        test.append(ExportFrame(f"heldout_{i:03d}", cam, view.rgb, view.distance if distances else None,
                                source.mask("heldout", i), keys))
    return train, test


class _RunSource:
    """The view source a run was made of, opened again from its record: a dataset's
    frames and masks, or the held-out ground truth of a run that has not written it."""

    def __init__(self, run_dir: Path, rec: dict):
        try:
            cfg = RunConfig(**rec["config"])
        except TypeError as exc:
            raise UserError(f"{run_dir}/run.json is damaged (its config: {first_line(exc)})") from None
        what = "dataset" if rec.get("candidate_files") else "scene"
        try:
            self.source = cfg.open_source()
        except UserError as exc:
            raise UserError(f"{run_dir}: exporting its held-out views needs its {what}, {cfg.scene}: "
                            f"{first_line(exc)}") from None
        if ([c.to_dict() for c in self.source.candidates] != rec["candidates"]
                or [c.to_dict() for c in self.source.heldout] != rec["heldout"]):
            raise UserError(f"{run_dir}: its {what}, {cfg.scene}, no longer has the run's views "
                            "(it changed since the run)")
        self._views = {}

    def view(self, kind: str, index: int):
        """The source's candidate or held-out view ``index`` (read once)."""
        if (kind, index) not in self._views:
            get = self.source.candidate_view if kind == "candidate" else self.source.heldout_view
            self._views[kind, index] = get(index)
        return self._views[kind, index]

    def mask(self, kind: str, index: int) -> np.ndarray | None:
        """(H, W) bool, True where a dataset view's alpha is not 0 (None: an image without alpha);
        a scene's: True where its ground truth hits geometry."""
        view = self.view(kind, index)
        if getattr(self.source, "candidate_frames", None) is None:
            return view.mask.copy()
        return None if view.background is None else ~view.known_empty

    def frame_keys(self, kind: str, index: int) -> dict:
        """A dataset frame's ``source_file_path`` and, when its image was undistorted or resampled,
        ``source_camera``: the image's intrinsics and lens, as transforms.json keys."""
        files = self.source.candidate_files if kind == "candidate" else self.source.heldout_files
        frame = (self.source.candidate_frames if kind == "candidate" else self.source.heldout_frames)[index]
        keys = {"source_file_path": files[index]}
        lens = frame.lens
        if lens is not None:
            keys["source_camera"] = {**lens.to_keys(), "fl_x": lens.fx, "fl_y": lens.fy, "cx": lens.cx,
                                     "cy": lens.cy, "w": lens.size[0], "h": lens.size[1]}
        return keys


def _read_distance(path: Path) -> np.ndarray:
    """(H, W) float32 channel ``Z`` of an EXR the run wrote."""
    return read_exr(path)["Z"]


def camera_keys(cam: Camera) -> dict:
    """A camera's intrinsics and lens as transforms.json keys (a pinhole's: ``OPENCV``, no distortion)."""
    k = cam.intrinsics()
    lens = {"camera_model": "OPENCV", "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0} if cam.lens is None \
        else cam.lens.to_keys()
    return {**lens, "camera_angle_x": math.radians(cam.fov), "fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]),
            "cx": float(k[0, 2]), "cy": float(k[1, 2])}


def _transforms(rec: dict, ref: Camera, distances: bool, masks: bool, frames: list) -> dict:
    """The content of a transforms file: the shared camera (``ref``'s), the scene's bounds, the frames."""
    data = {**camera_keys(ref), "w": ref.width, "h": ref.height}
    if rec.get("bbox"):  # the scene's bounds (runs recorded before they were kept have none)
        data["aabb"] = rec["bbox"]
    if distances:
        data["distance_note"] = ("distance_file_path: EXR channel Z, distance from the optical centre in scene "
                                 "units along each pixel-centre ray (not depth); 0 where nothing is hit")
    if masks:
        data["mask_note"] = ("mask_path: white where the view sees geometry, black where it sees only the "
                             "background (nerfstudio leaves black pixels out of its loss)")
    data["frames"] = frames
    return data


def _check_views(folder: Path, views: list[tuple[str, Camera]], distances: bool) -> None:
    """UserError unless every view's image (and distance map), ``folder/NAME.png`` (``.exr``),
    reads as an image of its camera's size: a damaged file is refused, not copied."""
    for name, cam in views:
        files = [(folder / f"{name}.png", lambda p: iio.imread(p, plugin="pillow").shape[:2])]
        if distances:
            files.append((folder / f"{name}.exr", lambda p: _read_distance(p).shape))
        for path, size_of in files:
            try:
                size = size_of(path)
            except Exception as exc:  # noqa: BLE001 (image readers raise many kinds)
                raise UserError(f"{path} is damaged (it does not read as an image: {first_line(exc)})") from None
            if tuple(size) != (cam.height, cam.width):
                raise UserError(f"{path} is damaged: {size[1]}x{size[0]} pixels where its camera has "
                                f"{cam.width}x{cam.height}")


def _earlier_export(out: Path) -> set[str]:
    """The image, mask and distance files an earlier export into ``out`` listed (only names that
    this module writes, so no other file is ever removed). UserError when ``out`` holds a
    dataset that no export wrote (a ``transforms*.json`` that is not an earlier export's):
    the export would replace or shadow it."""
    earlier = set()
    for path in sorted(out.glob("transforms*.json")) if out.is_dir() else []:
        frames = _exported_frames(path) if path.name in (ALL_FILE, TRAIN_FILE, TEST_FILE) else None
        if frames is None:
            raise FolderError(out, f"holds a dataset that is not an earlier export ({path.name}); "
                                   "export into another folder")
        names = {f.get(key) for f in frames for key in ("file_path", "distance_file_path", "mask_path")}
        earlier |= {n for n in names if isinstance(n, str) and _WRITTEN.fullmatch(n)}
    return earlier


def _exported_frames(path: Path) -> list[dict] | None:
    """The frames of ``path`` when it reads as a transforms file this module wrote (every
    frame names its candidate or held-out index and an image by the name an export gives it), else None."""
    try:
        frames = json.loads(path.read_text()).get("frames")
    except (OSError, ValueError, AttributeError, RecursionError):
        return None
    ours = bool(frames) and isinstance(frames, list) and all(
        isinstance(f, dict) and any(k in f for k in INDEX_KEYS) and isinstance(f.get("file_path"), str)
        and _WRITTEN.fullmatch(f["file_path"]) for f in frames)
    return frames if ours else None
