"""The interactive viewer of a run folder, on viser: cameras, each round's scores, captures and renders.

viser is an optional dependency (``pip install 'mitsuba-active[viewer]'``), imported when a viewer starts.
The page's first paint needs only the record and the cameras: the field and
its renderer load on the first click (:mod:`.ensembleimages`), the scene goes
out as one batch, and captured views as small JPEG thumbnails.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np

from .cameras import Camera
from .camerascene import camera_scene
from .errors import UserError
from .record import read_record, run_cameras

VIEWER_EXTRA = "pip install 'mitsuba-active[viewer]'"

#: Colours (RGB, 0-255) of the camera kinds; candidates are coloured by score.
HELDOUT_COLOUR, CAPTURED_COLOUR, INITIAL_COLOUR, UNSCORED_COLOUR = (30, 110, 220), (220, 30, 30), (200, 90, 0), \
    (170, 170, 170)

#: matplotlib's viridis (RGB, 0-255) at 17 even steps from 0 to 1: linear between them, within 5 of it.
VIRIDIS = np.array([[68, 1, 84], [72, 24, 106], [71, 45, 123], [66, 64, 134], [59, 82, 139], [51, 99, 141],
                    [44, 114, 142], [38, 130, 142], [33, 145, 140], [31, 160, 136], [40, 174, 128], [63, 188, 115],
                    [94, 201, 98], [132, 212, 75], [173, 220, 48], [216, 226, 25], [253, 231, 37]], dtype=float)

#: Longest side (pixels) of a captured view's thumbnail on its frustum, sent as JPEG of this quality.
THUMBNAIL_PX, THUMBNAIL_QUALITY = 64, 80


def _viser():
    try:
        import viser
    except ImportError:
        raise UserError(f"the viewer needs viser: {VIEWER_EXTRA}") from None
    return viser


def read_run(run_dir) -> dict:
    """The record of the run in ``run_dir``; UserError when the folder holds no run."""
    path = Path(run_dir) / "run.json"
    if not Path(run_dir).is_dir():
        raise UserError(f"{run_dir} is not a folder")
    if not path.is_file():
        raise UserError(f"{run_dir} holds no run (no run.json)")
    return read_record(path)


def path_segments(data: dict, shown: int) -> np.ndarray:
    """The way between the first ``shown`` captures of :func:`camera_scene`'s ``data``, as (N, 2, 3)
    line segments: each leg's recorded route where the camera moved, else a straight line."""
    points = [np.asarray(data["candidates"][i]["p"], dtype=float) for i in data["captured"][:shown]]
    routes = data.get("routes") or []
    segments = []
    for k in range(1, len(points)):
        route = np.asarray(routes[k], dtype=float) if k < len(routes) and routes[k] else np.stack(points[k - 1:k + 1])
        segments.extend(np.stack([route[:-1], route[1:]], axis=1))
    return np.asarray(segments, dtype=float).reshape(-1, 2, 3)


def opencv_wxyz(cam: dict) -> np.ndarray:
    """The quaternion (w, x, y, z) of a page camera (:func:`~.webpage.camera_scene`) in viser's
    OpenCV convention: +Z forward, +X right, +Y down."""
    from viser.transforms import SO3  # viser is an optional extra (see _viser)

    rot = np.stack([-np.asarray(cam["left"]), -np.asarray(cam["up"]), np.asarray(cam["fwd"])], axis=1)
    u, _, vt = np.linalg.svd(rot)  # the nearest rotation to the rounded axes
    return SO3.from_matrix(u @ vt).wxyz


def _vertical_fov(cam: dict) -> float:
    """Vertical field of view (radians) of a page camera, whose ``fov`` is horizontal, in degrees."""
    return float(2.0 * np.arctan(np.tan(np.radians(cam["fov"]) / 2.0) * cam["aspect"]))


def thumbnail(path) -> np.ndarray | None:
    """The image file ``path`` as RGB (h, w, 3) uint8, shrunk to at most :data:`THUMBNAIL_PX` a side
    (aspect kept); None when it is missing or unreadable."""
    # OpenCV, not PIL: the cameras' lenses have loaded it already.
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR) if Path(path).is_file() else None
    if bgr is None:
        return None
    h, w = bgr.shape[:2]
    scale = min(1.0, THUMBNAIL_PX / max(h, w))
    if scale < 1.0:
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        bgr = cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(bgr[..., ::-1])


def viridis(t: float) -> tuple[int, int, int]:
    """The colour (RGB, 0-255) of ``t`` in [0, 1] (clipped) on :data:`VIRIDIS`."""
    steps = np.linspace(0.0, 1.0, len(VIRIDIS))
    t = float(np.clip(t, 0.0, 1.0))
    return tuple(int(round(np.interp(t, steps, VIRIDIS[:, k]))) for k in range(3))


class RunViewer:
    """A viser server that shows the run in ``run_dir``; :meth:`refresh` reads the folder again."""

    def __init__(self, run_dir, host: str = "127.0.0.1", port: int = 8080):
        self.run_dir = Path(run_dir)
        self.rec = read_run(run_dir)
        viser = _viser()
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        self._lock = threading.Lock()
        self._ensemble = None  # the run's ensemble (ensembleimages.RunEnsemble), made on the first click
        self._gui_round = None
        self._path = None  # the line through the captured views, in capture order
        self.handles: dict = {}
        self.info = self.server.gui.add_markdown("Click a camera to render the ensemble's mean and variance from it.")
        self.mean_image = self.variance_image = None
        self.refresh(force=True)

    @property
    def port(self) -> int:
        return self.server.get_port()

    # -- drawing ------------------------------------------------------------
    def refresh(self, force: bool = False) -> bool:
        """Read run.json again and redraw when it changed (or ``force``); True when redrawn."""
        rec = read_run(self.run_dir) if not force else self.rec
        if not force and rec == self.rec:
            return False
        # One batch: a page applies the scene at once instead of over a frame per window of messages.
        with self._lock, self.server.atomic():
            self.rec = rec
            self.data = camera_scene(rec)
            self._make_slider()
            self._draw_static()
            self._draw_round()
        return True

    def _draw_static(self) -> None:
        scene, data = self.server.scene, self.data
        corners = np.asarray(data["corners"])
        edges = [(i, i | (1 << a)) for i in range(8) for a in range(3) if not i >> a & 1]
        scene.add_line_segments("/bounds", corners[np.array(edges)], colors=(120, 120, 120), thickness=1.5,
                                thickness_units="screen")
        extent = np.ptp(np.concatenate([corners, [c["p"] for c in data["candidates"]]]), axis=0).max()
        self.size = 0.035 * float(extent)
        for i, cam in enumerate(data["heldout"]):
            self._frustum(f"/heldout/{i:03d}", cam, 0.7, HELDOUT_COLOUR, ("heldout", i))
        # Drawn in the slider's round's colours: no second message per candidate to colour it.
        for i, (cam, colour) in enumerate(zip(data["candidates"], self._candidate_colours())):
            self._frustum(f"/candidates/{i:03d}", cam, 0.5, colour, ("candidate", i))

    def _frustum(self, name, cam, scale, colour, what, image=None, visible=True):
        handle = self.server.scene.add_camera_frustum(
            name, fov=_vertical_fov(cam), aspect=1.0 / cam["aspect"], scale=scale * self.size, color=colour,
            wxyz=opencv_wxyz(cam), position=np.asarray(cam["p"]), image=image, format="jpeg",
            jpeg_quality=THUMBNAIL_QUALITY, thickness=0.04 * scale * self.size, visible=visible)
        handle.on_click(lambda event, what=what: self._clicked(what))
        self.handles[name] = handle
        return handle

    def _make_slider(self) -> None:
        rounds = self.data["rounds"]
        if self._gui_round is not None:
            self._gui_round.remove()
            self._gui_round = None
        if rounds:
            self._gui_round = self.server.gui.add_slider("round", min=1, max=len(rounds), step=1,
                                                         initial_value=len(rounds))
            self._gui_round.on_update(self._on_round)

    def _on_round(self, _event) -> None:
        with self._lock, self.server.atomic():  # a slider's callback runs beside a refresh by --follow
            self._draw_round()

    def _round(self) -> dict | None:
        """The round the slider shows (None: the run has no rounds yet)."""
        rounds = self.data["rounds"]
        k = int(self._gui_round.value) - 1 if self._gui_round is not None else -1
        return rounds[k] if rounds else None

    def _candidate_colours(self) -> list[tuple[int, int, int]]:
        """Each candidate's colour: its score in the slider's round on viridis, grey where it has none."""
        r = self._round()
        scores = np.array([np.nan if s is None else s for s in (r or {}).get("scores") or []], dtype=float)
        finite = scores[np.isfinite(scores)] if scores.size else scores
        lo, hi = (finite.min(), finite.max()) if finite.size else (0.0, 1.0)
        colours = []
        for i in range(len(self.data["candidates"])):
            s = scores[i] if i < scores.size else np.nan
            colours.append(UNSCORED_COLOUR if not np.isfinite(s) else viridis((s - lo) / (hi - lo) if hi > lo else 0.5))
        return colours

    def _draw_round(self) -> None:
        """Colour the candidates by the chosen round's scores; show the views captured up to its end."""
        data, r = self.data, self._round()
        for i, colour in enumerate(self._candidate_colours()):
            self.handles[f"/candidates/{i:03d}"].color = colour  # viser sends only a changed colour
        shown = r["views"] if r else len(data["captured"])
        for n, i in enumerate(data["captured"]):
            name = f"/captured/{n:03d}"
            if name not in self.handles:
                self._frustum(name, data["candidates"][i], 1.2, INITIAL_COLOUR if n < data["initial"] else
                              CAPTURED_COLOUR, ("captured", n), image=self._view_image(n))
                self.server.scene.add_label(f"{name}/number", str(n))
            self.handles[name].visible = n < shown
        gone = [name for name in self.handles if name.startswith("/captured/") and
                int(name.rsplit("/", 1)[1]) >= len(data["captured"])]
        for name in gone:
            self.handles.pop(name).remove()
        if self._path is not None:
            self._path.remove()
            self._path = None
        segments = path_segments(data, shown)
        if len(segments):
            self._path = self.server.scene.add_line_segments("/path", segments, colors=CAPTURED_COLOUR,
                                                             thickness=2.0, thickness_units="screen")

    def _view_image(self, n: int) -> np.ndarray | None:
        return thumbnail(self.run_dir / "views" / f"view_{n:03d}.png")

    # -- rendering ------------------------------------------------------------
    def render(self, camera: Camera) -> dict | None:
        """The planner's ensemble's mean and variance images from ``camera`` (None: the run keeps no ensemble)."""
        # Here, not above: the field and Dr.Jit's renderer load on the first click, not while the page opens.
        from .ensembleimages import RunEnsemble

        if self._ensemble is None:
            self._ensemble = RunEnsemble(self.run_dir)
        return self._ensemble.render(self.rec, camera)

    def _clicked(self, what) -> None:
        kind, i = what
        cams = self.rec["heldout"] if kind == "heldout" else run_cameras(self.rec)  # with the cameras it added
        index = self.rec["captured"][i] if kind == "captured" else i
        text = {"candidate": f"candidate {i}", "heldout": f"held-out view {i}",
                "captured": f"capture #{i} (candidate {index})"}[kind]
        images = self.render(Camera.from_dict(cams[index]))
        if images is None:
            self.info.content = f"{text}: this run keeps no ensemble to render with"
            return
        self.info.content = f"{text}: the ensemble's mean and variance"
        for attr, key in (("mean_image", "mean"), ("variance_image", "variance")):
            handle = getattr(self, attr)
            if handle is None:
                setattr(self, attr, self.server.gui.add_image(images[key], label=key, format="png"))
            else:
                handle.image = images[key]

    # -- serving ------------------------------------------------------------
    def follow(self, stop: threading.Event, interval: float = 1.0) -> None:
        """Redraw whenever run.json changes, until ``stop`` is set."""
        path, stamp = self.run_dir / "run.json", None
        while not stop.wait(interval):
            try:
                now = path.stat().st_mtime_ns
            except OSError:
                continue
            if now != stamp:
                stamp = now
                try:
                    self.refresh()
                except UserError:  # a record being replaced: read it at the next change
                    stamp = None

    def close(self) -> None:
        self.server.stop()


def serve(run_dir, host: str = "127.0.0.1", port: int = 8080, follow: bool = False, log=print) -> None:
    """Show the run in ``run_dir`` until interrupted (Ctrl-C)."""
    t0 = time.perf_counter()
    viewer = RunViewer(run_dir, host, port)
    log(f"viewing {run_dir} at http://{host}:{viewer.port} (ready in {time.perf_counter() - t0:.1f} s); Ctrl-C stops")
    stop = threading.Event()
    try:
        if follow:
            viewer.follow(stop)
        else:
            stop.wait()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
