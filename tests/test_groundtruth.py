import ctypes
import re
import warnings

import numpy as np
import pytest

from mitsuba_active.groundtruth import GroundTruth, View
from mitsuba_active.imageio_utils import linear_to_srgb, read_exr, write_exr
from mitsuba_active.rigs import fibonacci_sphere
from mitsuba_active.scene import load_scene


def _ray_sphere(o, d, r):
    b = np.sum(o * d, axis=1)
    disc = b * b - (np.sum(o * o, axis=1) - r * r)
    t = -b - np.sqrt(np.maximum(disc, 0))
    return np.where(disc > 0, t, 0.0)


def test_distance_matches_the_analytic_sphere(sphere_xml, cache_dir):
    from mitsuba_active.cameras import camera_rays

    scene = load_scene(sphere_xml)
    gt = GroundTruth(scene, spp=4, cache_dir=cache_dir)
    for cam in fibonacci_sphere(3, [0, 0, 0], 1.7, 45.0, 32, 24):
        view = gt.render(cam)
        o, d = camera_rays(cam)
        # The icosphere's facets lie inside the radius-0.5 sphere: allow the tessellation gap.
        expected = _ray_sphere(o.astype(np.float64), d.astype(np.float64), 0.5).reshape(24, 32)
        inner = (expected > 0) & view.mask
        rel = np.abs(view.distance[inner] - expected[inner]) / expected[inner]
        assert inner.sum() > 100
        assert rel.max() < 0.01
        assert (view.distance[~view.mask] == 0).all()
        assert view.rgb.shape == (24, 32, 3) and 0 <= view.rgb.min() and view.rgb.max() <= 1


def test_distance_is_from_the_optical_centre_not_the_near_plane(sphere_xml):
    scene = load_scene(sphere_xml)
    cam = fibonacci_sphere(1, [0, 0, 0], 2.0, 30.0, 9, 9)[0]
    from mitsuba_active.cameras import Camera

    far_near = Camera(cam.to_world, cam.fov, 9, 9, near=1.0)
    gt = GroundTruth(scene, spp=1, cache_dir=False)
    assert abs(gt.render(far_near).distance[4, 4] - 1.5) < 0.01  # not 0.5


def test_cache_is_content_addressed_and_atomic(spot_xml, cache_dir):
    scene = load_scene(spot_xml)
    cam_a, cam_b = fibonacci_sphere(2, scene.center, 2.2, 40.0, 16, 16)
    gt = GroundTruth(scene, spp=4, cache_dir=cache_dir)
    first = gt.render(cam_a)
    files = sorted(cache_dir.rglob("*"))
    exrs = [f for f in files if f.suffix == ".exr"]
    assert len(exrs) == 1 and not [f for f in files if f.name.startswith(".")]
    again = gt.render(cam_a)
    assert np.array_equal(first.rgb, again.rgb) and np.array_equal(first.distance, again.distance)
    assert gt.key(cam_a) != gt.key(cam_b)
    assert gt.key(cam_a) != GroundTruth(scene, spp=8, cache_dir=cache_dir).key(cam_a)


def _wrong_size(path):
    write_exr(path, {"RGB": np.full((8, 8, 3), 0.5, np.float32), "Z": np.ones((8, 8), np.float32)})


def _with_nan(path):
    ch = read_exr(path)
    ch["RGB"][2:5, 3:7] = np.nan
    write_exr(path, ch)


def _with_inf(path):
    ch = read_exr(path)
    ch["Z"][0, 0] = np.inf
    write_exr(path, ch)


def _other_channels(path):
    ch = read_exr(path)
    write_exr(path, {"RGB": ch["RGB"]})


def _truncated(path):
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


def _garbled(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2:] = bytes(b ^ 0x5A for b in data[len(data) // 2:])  # the pixel data, past the header
    path.write_bytes(bytes(data))


def _not_an_exr(path):
    path.write_bytes(b"not an exr")


DAMAGES = {"wrong size": (_wrong_size, r"8x8 pixels, not 16x12"), "NaN": (_with_nan, "NaN or infinite"),
           "inf": (_with_inf, "NaN or infinite"), "other channels": (_other_channels, "channels RGB, not RGB and Z"),
           "truncated": (_truncated, "unreadable: "), "garbled": (_garbled, "unreadable: "),
           "not an EXR": (_not_an_exr, "unreadable: ")}


@pytest.fixture(scope="module")
def spot_view(spot_xml):
    """A 16x12 camera of the spot scene, and its view rendered without a cache."""
    scene = load_scene(spot_xml)
    cam = fibonacci_sphere(1, scene.center, 2.2, 40.0, 16, 12)[0]
    return scene, cam, GroundTruth(scene, spp=2, cache_dir=False).render(cam)


@pytest.mark.parametrize("damage", DAMAGES)
def test_a_bad_cache_entry_is_rendered_again_with_a_warning(spot_view, cache_dir, damage):
    """An entry that decodes to something other than its render (or not at
    all) is named in a warning, rendered again and replaced by a good one."""
    scene, cam, fresh = spot_view
    gt = GroundTruth(scene, spp=2, cache_dir=cache_dir)
    gt.render(cam)
    (entry,) = cache_dir.rglob("*.exr")
    spoil, why = DAMAGES[damage]
    spoil(entry)
    with pytest.warns(UserWarning, match=re.escape(f"cached ground truth {entry} is unusable (") + why) as caught:
        view = gt.render(cam)
    assert len(caught) == 1 and str(caught[0].message).endswith("; rendering it again")
    assert np.array_equal(view.rgb, fresh.rgb) and np.array_equal(view.distance, fresh.distance)
    assert np.array_equal(view.mask, fresh.mask)
    assert [p.name for p in cache_dir.rglob("*")] == [entry.parent.name, entry.name]  # no temporary file left
    stored = read_exr(entry)
    assert np.array_equal(linear_to_srgb(stored["RGB"]), fresh.rgb) and np.array_equal(stored["Z"], fresh.distance)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the replaced entry is good: read without a warning
        again = gt.render(cam)
    assert np.array_equal(again.rgb, fresh.rgb) and np.array_equal(again.distance, fresh.distance)


@pytest.mark.parametrize("damage", ["truncated", "garbled"])
def test_the_exr_librarys_messages_stay_off_stdout_and_stderr(spot_view, cache_dir, capfd, damage):
    """OpenEXR prints its complaints about a damaged file, on stderr from its
    C library and on stdout from its Python bindings."""
    scene, cam, _ = spot_view
    gt = GroundTruth(scene, spp=2, cache_dir=cache_dir)
    gt.render(cam)
    (entry,) = cache_dir.rglob("*.exr")
    DAMAGES[damage][0](entry)
    capfd.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gt.render(cam)
        DAMAGES[damage][0](entry)
        with pytest.raises(ValueError) as raised:
            read_exr(entry)
    ctypes.CDLL(None).fflush(None)  # what C printed into its buffer shows too
    assert capfd.readouterr() == ("", "")
    # The library's reason, without the file's name that the warning gives once.
    assert [str(w.message).count(str(entry)) for w in caught] == [1]
    assert re.fullmatch(r"\(EXR_ERR_\w+\) .+", str(raised.value)), raised.value
    assert f"unusable (unreadable: {raised.value});" in str(caught[0].message)


def test_shared_scenes_render_plausibly(shared_data):
    from tests.conftest import tiny_source

    for rel in ("mitsuba/simple/scene.xml", "mitsuba/cbox/cbox.xml"):
        src = tiny_source(shared_data / rel, n_candidates=4, n_heldout=2)
        view = src.candidate_view(0)
        assert view.mask.any() and view.rgb[view.mask].mean() > 0.02
        if src.scene.interior:
            assert view.mask.mean() > 0.5  # inside the room (open at the front) most rays meet a wall


def test_a_scene_without_an_integrator_is_path_traced(tmp_path):
    xml = tmp_path / "bare.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"/><emitter type="constant"/></scene>')
    cam = fibonacci_sphere(1, [0, 0, 0], 4.0, 40.0, 8, 8)[0]
    view = GroundTruth(load_scene(xml), spp=2, cache_dir=False).render(cam)
    # A white diffuse sphere under a unit white sky: lit, not black, and hit in the middle.
    assert view.mask[4, 4] and 0.2 < view.rgb[4, 4].mean() <= 1.0


def test_a_scene_without_lights_is_flagged(tmp_path):
    import pytest

    xml = tmp_path / "dark.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    with pytest.warns(UserWarning, match="no lights"):
        load_scene(xml)


def test_large_renders_are_split_into_passes_of_fewer_samples(spot_xml, monkeypatch):
    """Mitsuba traces a render's samples at once: past MAX_PASS_SAMPLES they
    are rendered in passes and averaged, which estimates the same image."""
    import mitsuba as mi

    import mitsuba_active.groundtruth as gt

    scene = load_scene(spot_xml)
    cam = fibonacci_sphere(1, scene.center, 3.0 * scene.radius, width=24, height=24)[0]
    whole = gt.render_rgb(scene.mi_scene, cam, spp=64, seed=1)
    calls = []
    render = mi.render
    monkeypatch.setattr(mi, "render", lambda *a, **k: calls.append(k["spp"]) or render(*a, **k))
    monkeypatch.setattr(gt, "MAX_PASS_SAMPLES", 24 * 24 * 20)
    passes = gt.render_rgb(scene.mi_scene, cam, spp=64, seed=1)
    assert calls == [20, 20, 20, 4] and passes.dtype == np.float32 and passes.shape == (24, 24, 3)
    assert abs(passes.mean() - whole.mean()) < 0.01 and np.abs(passes - whole).mean() < 0.05


def test_render_command_replaces_an_earlier_render_whole(spot_xml, tmp_path, monkeypatch):
    """A render over an earlier one leaves only its own views (and the user's
    files); an interrupted render leaves the earlier one as it was."""
    from click.testing import CliRunner

    import mitsuba_active.renders as renders
    from mitsuba_active.cli import main

    out = tmp_path / "views"
    tiny = ["--resolution", "8", "--spp", "1", "--candidates", "4", "--heldout", "1"]

    def render(*args):
        result = CliRunner().invoke(main, ["render", str(spot_xml), "-o", str(out), *tiny, *args])
        return result.exit_code, result.output

    code, text = render()
    assert code == 0 and "rendering: 100%" in text, text
    (out / "notes.txt").write_text("mine")
    code, text = render("--views", "2", "--quiet")
    assert code == 0 and "rendering" not in text, text
    names = sorted(p.name for p in out.iterdir())
    assert names == ["cameras.json", "cand_000.exr", "cand_000.png", "cand_000_distance.png",
                     "cand_001.exr", "cand_001.png", "cand_001_distance.png", "notes.txt"], names
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    written = []
    write_png = renders.write_png

    def interrupted_at_the_second_view(path, img):
        written.append(path)
        if len(written) == 3:
            raise KeyboardInterrupt
        write_png(path, img)

    monkeypatch.setattr(renders, "write_png", interrupted_at_the_second_view)
    code, text = render()
    assert code == 130 and "\nmitsuba-active: interrupted\n" in text, text  # on a line of its own
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_rendered_views_empty_pixels_keep_off_the_edges():
    """A pixel averages its footprint: one beside a hit may show the object's edge, so it is not known empty."""
    mask = np.zeros((6, 7), bool)
    mask[2, 3] = True
    view = View(np.ones((6, 7, 3), np.float32), np.zeros((6, 7), np.float32), mask, camera=None)
    near = np.zeros_like(mask)
    near[1:4, 2:5] = True
    assert np.array_equal(view.empty, ~near) and view.background is None
    given = np.zeros_like(mask)
    assert View(view.rgb, view.distance, mask, None, known_empty=given).empty is given


def test_an_exr_the_library_cannot_write_is_an_oserror_and_leaves_nothing(tmp_path, monkeypatch):
    import OpenEXR

    def full_disk(self, name):
        raise RuntimeError("Failed to write pixel data: No space left on device")

    monkeypatch.setattr(OpenEXR.File, "write", full_disk)
    with pytest.raises(OSError) as raised:
        write_exr(tmp_path / "a.exr", {"RGB": np.zeros((2, 2, 3))})
    assert raised.value.filename == str(tmp_path / "a.exr")
    assert raised.value.strerror == "Failed to write pixel data: No space left on device"
    assert list(tmp_path.iterdir()) == []
