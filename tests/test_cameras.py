import mitsuba as mi
import numpy as np
import pytest

from mitsuba_active.cameras import MITSUBA_TO_OPENGL, Camera, camera_rays, look_at
from mitsuba_active.errors import UserError
from mitsuba_active.field import FieldConfig
from mitsuba_active.field.room import ROOM_OPTIONS
from mitsuba_active.rigs import (INTERIOR_CLEARANCE, _room_ellipsoid, check_disjoint, fibonacci_directions,
                                 fibonacci_sphere, hemisphere, interior, rings, room_for_camera, scene_rigs)
from mitsuba_active.scene import load_scene, scene_from_mitsuba


@pytest.mark.parametrize("rig", [fibonacci_sphere, hemisphere, rings])
def test_rigs_look_at_the_centre_from_the_radius(rig):
    c = np.array([0.1, -0.2, 0.3])
    cams = rig(17, c, 2.5, 50.0, 8, 6)
    assert len(cams) == 17
    for cam in cams:
        assert np.linalg.norm(cam.position - c) == pytest.approx(2.5)
        to_c = (c - cam.position) / 2.5
        assert np.dot(cam.forward, to_c) == pytest.approx(1.0)
        assert np.allclose(cam.to_world[:3, :3].T @ cam.to_world[:3, :3], np.eye(3), atol=1e-9)
    if rig is hemisphere:
        assert all(cam.position[1] > c[1] for cam in cams)


def test_interior_rig_keeps_the_rooms_up_direction():
    for up in ([0, 1, 0], [0, 0, 1]):
        cams = interior(20, [-1, -1, -1], [1, 1, 1], up=up)
        level = [c for c in cams if abs(np.dot(c.forward, up)) < 0.9]  # not looking straight up or down
        assert len(level) > 10
        assert all(abs(np.dot(c.to_world[:3, 0], up)) < 1e-9 and np.dot(c.to_world[:3, 1], up) > 0 for c in level)


def test_heldout_rig_is_disjoint_and_duplicates_are_caught(spot_xml):
    scene = load_scene(spot_xml)
    cands, held = scene_rigs(scene, "sphere", 30, 10, 8)
    assert len(cands) == 30 and len(held) == 10
    with pytest.raises(UserError):
        check_disjoint(cands, [cands[3]])


@pytest.mark.parametrize("rig", [fibonacci_sphere, hemisphere, rings])
def test_heldout_offset_never_reproduces_a_candidate(rig):
    # Counts whose rings used to line up (e.g. 100 candidates, 5 held-out views).
    for n_cand, n_held in ((100, 5), (100, 30), (60, 20), (34, 20), (9, 3)):
        check_disjoint(rig(n_cand, (0, 0, 0), 2.0), rig(n_held, (0, 0, 0), 2.0, offset=0.5))


@pytest.mark.parametrize("rig", ["sphere", "hemisphere", "interior"])
def test_heldout_views_lie_between_candidates(spot_xml, shared_data, rig):
    """Each held-out view keeps away from every candidate (a held-out view next to a candidate would
    score a planner that picked it on a view it trained on) and from the other held-out views."""
    scene = load_scene(shared_data / "mitsuba/cbox/cbox.xml" if rig == "interior" else spot_xml)
    cands, held = scene_rigs(scene, rig, 100, 20, 8)
    # Where each camera sits on its rig, seen from the rig's centre (all look at it).
    centre = 0.5 * (scene.bbox_min + scene.bbox_max) if rig == "interior" else scene.center
    c, h = (np.stack([cam.position - centre for cam in cams]) for cams in (cands, held))
    if rig == "interior":  # an ellipsoid: compare places on it as directions of the unit sphere
        c, h = c / (scene.bbox_max - scene.bbox_min), h / (scene.bbox_max - scene.bbox_min)
    c, h = c / np.linalg.norm(c, axis=1, keepdims=True), h / np.linalg.norm(h, axis=1, keepdims=True)
    angle = lambda a, b: np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))  # noqa: E731
    spacing = np.median(np.sort(angle(c, c), axis=1)[:, 1])  # a candidate's nearest neighbour
    assert angle(h, c).min() > 0.45 * spacing
    assert np.sort(angle(h, h), axis=1)[:, 1].min() > 0.45 * spacing
    # Spread as the candidates are: not crowded into one part of the rig, such as a hemisphere's rim.
    up = scene.up if rig != "interior" else np.array([0.0, 1.0, 0.0])
    height = [np.degrees(np.arcsin(np.clip(v @ up, -1, 1))) for v in (c, h)]
    assert abs(np.median(height[1]) - np.median(height[0])) < 12
    if rig == "hemisphere":  # above the floor, as the candidates are, and not along its rim
        assert (height[1] > 4.9).all() and (height[1] < 8).sum() <= 4
    if rig == "interior":  # the candidates cover every height of the ellipsoid that has room for a camera
        places = fibonacci_directions(400)
        ok = places[room_for_camera(scene, centre + _room_ellipsoid(scene.bbox_min, scene.bbox_max)[1] * places)]
        room = np.degrees(np.arcsin(np.clip(ok @ up, -1, 1)))
        assert height[0].min() < room.min() + 5 and height[0].max() > room.max() - 5


def test_heldout_views_stay_distinct_and_off_the_rim_with_few_candidates(spot_xml, shared_data):
    """Many held-out views in a furnished room are all distinct; with few candidates, a hemisphere's
    held-out views do not crowd along its rim (below 8 degrees: 6 % of its area)."""
    room = load_scene(shared_data / "mitsuba/cbox/cbox.xml")
    _, held = scene_rigs(room, "interior", 100, 100, 8)
    assert len({cam.to_world.tobytes() for cam in held}) == 100
    scene = load_scene(spot_xml)
    _, held = scene_rigs(scene, "hemisphere", 1, 20, 8)
    height = np.degrees(np.arcsin(np.clip(-np.stack([cam.forward for cam in held]) @ scene.up, -1, 1)))
    assert (height < 8).sum() <= 3


def test_clearance_is_the_distance_to_the_nearest_surface():
    ball = scene_from_mitsuba(mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 2.0},
                                              "light": {"type": "constant"}}))
    got = ball.clearance(np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 5.0]]))
    assert got == pytest.approx([2.0, 0.5, 1.0, 3.0], rel=0.01)


def test_interior_cameras_keep_the_room_fields_clearance(shared_data):
    """No generated interior camera stands closer to a surface than a room's field starts its samples."""
    room = load_scene(shared_data / "mitsuba/cbox/cbox.xml")
    diag = np.linalg.norm(room.bbox_max - room.bbox_min)
    cands, held = scene_rigs(room, "interior", 100, 20, 8)
    for cams in (cands, held):
        assert room.clearance(np.stack([c.position for c in cams])).min() >= INTERIOR_CLEARANCE * diag
    # The room field's near, on its padded box, is the same distance.
    padded = diag * (1 + 2 * FieldConfig.bbox_padding)
    assert ROOM_OPTIONS["near"] * padded == pytest.approx(INTERIOR_CLEARANCE * diag, rel=1e-4)
    # Without the clearance some of these places would stand closer: the test can tell.
    center, axes = _room_ellipsoid(room.bbox_min, room.bbox_max)
    places = center + axes * fibonacci_directions(400)
    assert (room.clearance(places[room.free_space(places)]) < INTERIOR_CLEARANCE * diag).any()


def test_xml_rig_uses_the_scenes_own_sensor(shared_data):
    scene = load_scene(shared_data / "mitsuba/simple/scene.xml")
    cands, held = scene_rigs(scene, "xml", n_heldout=5, width=8)
    assert len(cands) == 1 and np.allclose(cands[0].position, [0, -12, 5], atol=1e-4)
    assert len(held) == 5


def test_xml_rig_says_it_centres_off_centre_sensors(tmp_path):
    sensor = ('<sensor type="perspective"><float name="fov" value="40"/>{}<transform name="to_world">'
              '<lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform></sensor>')
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><emitter type="constant"/><shape type="sphere"/>'
                   + sensor.format('<float name="principal_point_offset_x" value="0.1"/>') + sensor.format("")
                   + "</scene>")
    scene = load_scene(xml)
    assert scene.sensors_off_centre == 1
    with pytest.warns(UserWarning, match="1 of the 2 sensors of .*s.xml have a principal point offset"):
        cands, _ = scene_rigs(scene, "xml", n_heldout=2, width=8)
    assert len(cands) == 2
    # A thin-lens camera has no principal point offset to read.
    xml.write_text('<scene version="3.0.0"><emitter type="constant"/><shape type="sphere"/>'
                   + sensor.format("").replace('type="perspective">', 'type="thinlens"><float name="aperture_radius" '
                                               'value="0.01"/><float name="focus_distance" value="4"/>')
                   + "</scene>")
    assert load_scene(xml).sensors_off_centre == 0 and len(load_scene(xml).sensors) == 1


def test_xml_rig_keeps_a_crop_windows_view_and_names_what_it_does_not_keep(tmp_path):
    import math

    def scene(sensor_type="perspective", extra="", film="", transform=""):
        xml = tmp_path / "s.xml"
        xml.write_text('<scene version="3.0.0"><emitter type="constant"/><shape type="sphere"/>'
                       f'<sensor type="{sensor_type}"><float name="fov" value="40"/>{extra}<transform name="to_world">'
                       f'{transform}<lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>'
                       f'<film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/>'
                       f'{film}</film></sensor></scene>')
        return load_scene(xml)

    def crop(x, y):
        return "".join(f'<integer name="{name}" value="{value}"/>' for name, value in
                       (("crop_width", 16), ("crop_height", 16), ("crop_offset_x", x), ("crop_offset_y", y)))

    # A centred crop window sees the middle of the film's field of view: half as wide in tangent.
    centred = scene(film=crop(8, 8))
    (cam,) = centred.sensors
    assert (cam.width, cam.height, centred.sensors_off_centre) == (16, 16, 0)
    assert math.isclose(math.tan(math.radians(cam.fov) / 2), math.tan(math.radians(20)) / 2, rel_tol=1e-6)
    # Centred but for the half pixel of an odd difference in size: centred.
    assert scene(film=crop(8, 8).replace('"crop_width" value="16"', '"crop_width" value="15"')).sensors_off_centre == 0
    # Off the film's centre, it looks off-axis: centred, as a principal point offset is, with a warning.
    corner = scene(film=crop(16, 0))
    assert corner.sensors_off_centre == 1
    with pytest.warns(UserWarning, match="a crop window off the film's centre"):
        scene_rigs(corner, "xml", n_heldout=2, width=8)
    # A thin lens is rendered as a pinhole.
    thin = scene("thinlens", '<float name="aperture_radius" value="0.1"/><float name="focus_distance" value="4"/>')
    assert thin.sensors_thin_lens == 1
    with pytest.warns(UserWarning, match="1 of the 1 sensors of .*s.xml are thin-lens cameras, .* no defocus"):
        scene_rigs(thin, "xml", n_heldout=2, width=8)
    # A mirrored sensor has no camera pose: refused for rig 'xml', while other rigs need no sensor.
    mirrored = scene(transform='<scale x="-1"/>')
    with pytest.raises(UserError, match="the to_world of sensor 0 of .*s.xml is not a rigid motion: .* det -1"):
        scene_rigs(mirrored, "xml", n_heldout=2, width=8)
    assert len(scene_rigs(mirrored, "sphere", 4, 2, 8)[0]) == 4


def test_rays_agree_with_intrinsics_and_pose():
    cam = Camera(look_at([1, 2, 3], [0, 0, 0]), fov=60.0, width=8, height=6)
    o, d = camera_rays(cam)
    assert o.shape == (48, 3) and d.shape == (48, 3)
    assert np.allclose(o, cam.position, atol=1e-5)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    # Project every ray with K in the OpenCV frame: it must land on its pixel centre.
    cv = cam.to_world @ np.diag([-1.0, -1.0, 1.0, 1.0])
    local = d @ cv[:3, :3]  # world -> camera (rotation is orthonormal)
    uv = (cam.intrinsics() @ (local / local[:, 2:3]).T).T[:, :2]
    ys, xs = np.mgrid[0:6, 0:8]
    assert np.allclose(uv, np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], 1), atol=1e-3)


def test_opengl_conversion_round_trips():
    m = look_at([1, 2, 3], [0, 0.5, 0])
    gl = m @ MITSUBA_TO_OPENGL
    assert np.allclose(-gl[:3, 2], m[:3, 2])  # OpenGL cameras look along -Z
    assert np.allclose(gl @ MITSUBA_TO_OPENGL, m)


def test_camera_validation():
    with pytest.raises(UserError):
        Camera(np.eye(4), 40.0, 0, 16)
    with pytest.raises(UserError):
        Camera(np.eye(4), 200.0, 16, 16)
    cam = Camera.from_dict(Camera(look_at([0, 0, 2], [0, 0, 0]), 45.0, 5, 4).to_dict())
    assert (cam.width, cam.height, cam.fov) == (5, 4, 45.0)
