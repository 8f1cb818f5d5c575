import shutil

import numpy as np
import mitsuba as mi
import pytest

from mitsuba_active.scene import DEFAULT_COLOR, load_scene, normalise_vertices, scene_from_mesh


def test_spot_scene_is_textured_normalised_and_loads_in_plain_mitsuba(spot_xml):
    text = spot_xml.read_text()
    assert 'type="bitmap"' in text and "spot_texture.png" in text
    assert (spot_xml.parent / "spot.ply").is_file()
    plain = mi.load_file(str(spot_xml))  # no mitsuba_active code involved
    bbox = plain.bbox()
    extent = np.array(bbox.max) - np.array(bbox.min)
    assert np.isclose(extent.max(), 1.0, atol=1e-4)
    assert np.allclose(np.array(bbox.max) + np.array(bbox.min), 0.0, atol=1e-4)


def test_a_texture_given_beside_the_mesh_leaves_the_meshs_own_alone(tmp_path, shared_data):
    import shutil

    from PIL import Image

    for name in ("spot.obj", "spot_texture.png"):
        shutil.copyfile(shared_data / "meshes" / name, tmp_path / name)
    own = (tmp_path / "spot_texture.png").read_bytes()
    Image.new("RGB", (8, 8), (200, 30, 30)).save(tmp_path / "red.png")
    xml = scene_from_mesh(tmp_path / "spot.obj", tmp_path / "spot.xml", texture=tmp_path / "red.png")
    assert (tmp_path / "spot_texture.png").read_bytes() == own
    assert 'value="spot_scene_texture.png"' in xml.read_text()
    assert (tmp_path / "spot_scene_texture.png").read_bytes() == (tmp_path / "red.png").read_bytes()
    # Without --texture the mesh's own is used where it lies.
    xml = scene_from_mesh(tmp_path / "spot.obj", tmp_path / "spot.xml")
    assert 'value="spot_texture.png"' in xml.read_text() and (tmp_path / "spot_texture.png").read_bytes() == own
    # The XML being replaced names the mesh's own texture: it stays all the same.
    xml = scene_from_mesh(tmp_path / "spot.obj", tmp_path / "spot.xml", texture=tmp_path / "red.png")
    assert (tmp_path / "spot_texture.png").read_bytes() == own and 'value="spot_scene_texture.png"' in xml.read_text()


def test_mesh_names_that_xml_or_mitsuba_would_misread_are_written_plainly(tmp_path, shared_data):
    import shutil

    mesh = tmp_path / 'R&D "v2" $res.obj'
    shutil.copyfile(shared_data / "meshes" / "suzanne.obj", mesh)
    xml = scene_from_mesh(mesh, tmp_path / "out" / "s.xml")
    assert (tmp_path / "out" / "R_D__v2___res.ply").is_file()
    scene = load_scene(xml)  # the XML parses, and Mitsuba finds the mesh
    assert np.isclose(np.max(scene.bbox_max - scene.bbox_min), 1.0, atol=1e-4)


def test_a_mesh_of_any_size_is_normalised(tmp_path, shared_data):
    import trimesh

    mesh = trimesh.load(shared_data / "meshes" / "suzanne.obj", force="mesh")
    mesh.apply_scale(1e-7)  # a microscopic part, in metres
    mesh.export(tmp_path / "tiny.ply")
    scene = load_scene(scene_from_mesh(tmp_path / "tiny.ply", tmp_path / "tiny.xml"))
    assert np.isclose(np.max(scene.bbox_max - scene.bbox_min), 1.0, atol=1e-4)


def test_a_meshs_vertex_colours_are_its_reflectance(tmp_path, shared_data):
    import trimesh

    from mitsuba_active.cameras import Camera, look_at

    mesh = trimesh.load(shared_data / "meshes" / "suzanne.obj", force="mesh")
    red = np.tile([200, 30, 30, 255], (len(mesh.vertices), 1)).astype(np.uint8)
    mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=red)
    mesh.export(tmp_path / "red.ply")
    cam = Camera(look_at([0, 0, 2.5], [0, 0, 0]), fov=30.0, width=16, height=16)

    def centre_pixel(**options):
        xml = scene_from_mesh(tmp_path / "red.ply", tmp_path / "out" / "s.xml", **options)
        return np.array(mi.render(load_scene(xml).mi_scene, sensor=cam.sensor(16)))[8, 8]

    r, g, b = centre_pixel()
    assert r > 3 * g and r > 3 * b
    # Kept as well beside texture coordinates (trimesh then holds them among the vertex attributes).
    header = (f"ply\nformat ascii 1.0\nelement vertex {len(mesh.vertices)}\n"
              + "".join(f"property float {p}\n" for p in "xyzst")
              + "".join(f"property uchar {c}\n" for c in ("red", "green", "blue"))
              + f"element face {len(mesh.faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = [f"{x} {y} {z} 0.5 0.5 200 30 30" for x, y, z in mesh.vertices]
    rows += [f"3 {a} {b} {c}" for a, b, c in mesh.faces]
    (tmp_path / "red_uv.ply").write_text(header + "\n".join(rows) + "\n")
    assert trimesh.load(tmp_path / "red_uv.ply", force="mesh").visual.kind == "texture"
    assert "vertex_color" in scene_from_mesh(tmp_path / "red_uv.ply", tmp_path / "uv" / "s.xml").read_text()
    r, g, b = centre_pixel(texture=False, color=(0.2, 0.2, 0.8))  # --no-texture: the plain colour
    assert b > 2 * r


def _two_material_obj(folder, kd_top="0.8 0.05 0.05", kd_bottom="0.05 0.05 0.8", uv=False):
    """A unit cube in an OBJ whose top half (y > 0) and bottom half use two materials of their own colours
    (with texture coordinates if ``uv``)."""
    import trimesh

    box = trimesh.creation.box(extents=(1, 1, 1))
    top = box.triangles_center[:, 1] > 0.25
    lines = ["mtllib box.mtl"] + [f"v {x} {y} {z}" for x, y, z in box.vertices]
    lines += [f"vt {0.5 + 0.4 * x} {0.5 + 0.4 * z}" for x, _, z in box.vertices] if uv else []
    for name, faces in (("top", box.faces[top]), ("bottom", box.faces[~top])):
        lines += [f"usemtl {name}"] + [" ".join(["f"] + [f"{i + 1}/{i + 1}" if uv else f"{i + 1}" for i in face])
                                       for face in faces]
    (folder / "box.obj").write_text("\n".join(lines) + "\n")
    (folder / "box.mtl").write_text(f"newmtl top\nKd {kd_top}\nnewmtl bottom\nKd {kd_bottom}\n")
    return folder / "box.obj"


def test_a_meshs_material_colours_are_its_reflectance(tmp_path):
    """An OBJ material's Kd and a glTF material's baseColorFactor (both linear) colour an untextured mesh."""
    import trimesh

    from mitsuba_active.cameras import Camera, look_at

    def pixels(mesh, name, at, **options):  # the centre pixel seen from each of ``at``
        scene = load_scene(scene_from_mesh(mesh, tmp_path / name / "s.xml", **options))
        return [np.array(mi.render(scene.mi_scene, sensor=Camera(look_at(p, [0, 0, 0]), fov=20.0, width=8,
                                                                   height=8).sensor(4)))[4, 4] for p in at]

    obj = _two_material_obj(tmp_path)
    top, bottom = pixels(obj, "two", ([0, 3, 0.01], [0, -3, 0.01]))
    assert top[0] > 4 * top[2] and bottom[2] > 4 * bottom[0]  # each half in its own material's colour
    for colour in pixels(obj, "given", ([0, 3, 0.01], [0, -3, 0.01]), color=(0.1, 0.7, 0.1)):
        assert colour[1] > 4 * colour[0]  # a colour given wins
    shade = np.array(DEFAULT_COLOR) / sum(DEFAULT_COLOR)  # several colours, none taken: the default's hue
    assert all(np.allclose(c / c.sum(), shade, atol=0.02) for c in pixels(obj, "plain", ([0, 3, 0.01],),
                                                                          texture=False))

    # One material: its colour, as the XML's plain reflectance, equal to the file's linear numbers.
    one = tmp_path / "one"
    one.mkdir()
    obj = _two_material_obj(one, kd_bottom="0.8 0.05 0.05")
    assert 'value="0.8 0.05 0.05"' in scene_from_mesh(obj, one / "s.xml").read_text()
    (one / "box.mtl").write_text("newmtl top\nKs 0.5 0.5 0.5\nnewmtl bottom\nKs 0.2 0.2 0.2\n")  # no colours
    default = " ".join(f"{c:g}" for c in DEFAULT_COLOR)
    assert f'value="{default}"' in scene_from_mesh(obj, one / "s.xml").read_text()

    # A part whose material names no colour (none, or not a number) takes the default; the others keep theirs.
    for name, kd_top in (("nan", "nan nan nan"), ("none", "")):  # a bare "Kd": trimesh reads no colour
        (tmp_path / name).mkdir()
        top, bottom = pixels(_two_material_obj(tmp_path / name, kd_top=kd_top), f"{name}_out",
                             ([0, 3, 0.01], [0, -3, 0.01]))
        assert np.isfinite(top).all() and np.allclose(top / top.sum(), shade, atol=0.02) and bottom[2] > 4 * bottom[0]
    # With several materials, an image named like the mesh is its texture (on the file's own UVs), as with one.
    from PIL import Image

    textured = tmp_path / "textured"
    textured.mkdir()
    Image.new("RGB", (8, 8), (30, 200, 30)).save(textured / "box_texture.png")
    obj = _two_material_obj(textured, uv=True)
    assert "box_texture.png" in scene_from_mesh(obj, textured / "out" / "s.xml").read_text()
    for colour in pixels(obj, "textured_out", ([0, 3, 0.01], [0, -3, 0.01])):
        assert colour[1] > 4 * colour[0]

    box = trimesh.creation.box()
    box.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(
        baseColorFactor=[51, 204, 51, 255]))
    box.export(tmp_path / "box.glb")
    assert 'value="0.2 0.8 0.2"' in scene_from_mesh(tmp_path / "box.glb", tmp_path / "glb" / "s.xml").read_text()


def test_two_sided_surfaces_reflect_from_behind(tmp_path):
    import trimesh

    from mitsuba_active.cameras import Camera, look_at

    sheet = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])  # faces +z
    sheet.export(tmp_path / "sheet.ply")
    behind = Camera(look_at([0, 0, -2], [0, 0, 0]), fov=20.0, width=8, height=8)
    seen = {}
    for two_sided in (False, True):
        xml = scene_from_mesh(tmp_path / "sheet.ply", tmp_path / f"{two_sided}" / "s.xml", two_sided=two_sided)
        seen[two_sided] = float(np.array(mi.render(load_scene(xml).mi_scene, sensor=behind.sensor(4))).mean())
    assert seen[False] < 0.01 and seen[True] > 0.2


def test_up_axis_rotates_z_up_meshes_to_y_up():
    v = np.array([[0, 0, 0], [0.1, 0.2, 3.0]])  # tall along z
    y_up = normalise_vertices(v, "z")
    assert np.ptp(y_up[:, 1]) == pytest.approx(1.0)
    assert np.ptp(normalise_vertices(v, "y")[:, 2]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="up must be 'y' or 'z', got 'x'"):
        normalise_vertices(v, "x")


def test_lights_floor_and_plain_colour(tmp_path, shared_data):
    xml = scene_from_mesh(shared_data / "meshes" / "suzanne.obj", tmp_path / "s.xml", sun=True, point_lights=2,
                          floor=True, color=(0.2, 0.4, 0.8))
    text = xml.read_text()
    assert 'type="directional"' in text and text.count('type="point"') == 2
    assert 'id="floor"' in text and "0.2 0.4 0.8" in text and "bitmap" not in text
    scene = load_scene(xml)
    # The floor is a platform a little wider than the object (which spans 1).
    assert 1.5 < scene.bbox_max[0] - scene.bbox_min[0] < 2.0
    assert len(scene.mi_scene.emitters()) == 4
    # The automatic rig stays above the floor: from below, a view shows its underside only.
    from mitsuba_active.rigs import scene_rigs

    assert scene.floor and not load_scene(shared_data / "mitsuba" / "simple" / "scene.xml").floor
    floor_height = scene.bbox_min @ scene.up
    for cams in scene_rigs(scene, "auto", 40, 10):
        assert min(c.position @ scene.up for c in cams) > floor_height


@pytest.mark.parametrize("name", ["cow.obj", "teapot.obj", "suzanne.obj"])
def test_the_floor_lies_just_under_the_object(tmp_path, shared_data, name):
    scene = load_scene(scene_from_mesh(shared_data / "meshes" / name, tmp_path / "s.xml", floor=True))
    heights = {shape.id(): (shape.bbox().min.y, shape.bbox().max.y) for shape in scene.mi_scene.shapes()}
    assert 0 < heights["object"][0] - heights["floor"][1] < 0.002


def test_a_glb_meshs_own_texture_is_used(tmp_path, shared_data):
    """glTF/GLB keep their texture in a PBR material's baseColorTexture, not in an OBJ material's image."""
    import trimesh
    from PIL import Image

    mesh = trimesh.load(shared_data / "meshes" / "spot.obj", force="mesh")
    texture = Image.open(shared_data / "meshes" / "spot_texture.png").convert("RGB")
    mesh.visual = trimesh.visual.TextureVisuals(uv=mesh.visual.uv, image=texture)
    mesh.export(tmp_path / "spot.glb")
    xml = scene_from_mesh(tmp_path / "spot.glb", tmp_path / "out" / "spot.xml")
    assert "bitmap" in xml.read_text()
    written = np.asarray(Image.open(tmp_path / "out" / "spot_texture.png").convert("RGB"))
    assert np.array_equal(written, np.asarray(texture))


def test_a_text_mesh_that_is_not_utf8_reads(tmp_path, shared_data):
    obj = tmp_path / "latin1.obj"
    obj.write_bytes(b"# mod\xe8le\n" + (shared_data / "meshes" / "suzanne.obj").read_bytes())
    assert load_scene(scene_from_mesh(obj, tmp_path / "s.xml")).bbox_max[0] > 0


@pytest.mark.parametrize("rel,interior", [("mitsuba/simple/scene.xml", False), ("mitsuba/cbox/cbox.xml", True),
                                          ("mitsuba/cbox/cbox-rgb.xml", True)])
def test_shared_mitsuba_scenes_load_unchanged(shared_data, rel, interior):
    scene = load_scene(shared_data / rel)
    assert scene.interior is interior
    assert len(scene.sensors) == 1 and scene.sensors[0].width == 256
    assert (scene.bbox_max > scene.bbox_min).all()


def _cup(radius=0.5):
    import trimesh

    wall = trimesh.creation.annulus(r_min=0.84 * radius, r_max=radius, height=1.0)
    bottom = trimesh.creation.cylinder(radius=radius, height=0.08)
    bottom.apply_translation([0, 0, -0.46])
    return trimesh.util.concatenate([wall, bottom])  # z up


def _open_front_room():
    """The Cornell box's layout, of solid walls."""
    import trimesh

    def slab(extents, at):
        box = trimesh.creation.box(extents=extents)
        box.apply_translation(at)
        return box

    return trimesh.util.concatenate([slab([4, 0.2, 4], [0, -1.25, 0]), slab([4, 0.2, 4], [0, 1.25, 0]),
                                     slab([0.2, 2.5, 4], [-2, 0, 0]), slab([0.2, 2.5, 4], [2, 0, 0]),
                                     slab([4, 2.5, 0.2], [0, 0, -2]), slab([0.8, 0.7, 0.5], [1.2, -0.9, 1.0])])


def _room(pillar=True, outer_walls=False):
    import trimesh

    room = trimesh.creation.box(extents=[4, 2.5, 4])
    room.invert()  # walls facing in
    table = trimesh.creation.box(extents=[0.8, 0.7, 0.5])
    table.apply_translation([1.2, -0.9, 1.0])
    parts = [room, table]
    if pillar:  # right where the box's centre is
        parts.append(trimesh.creation.box(extents=[0.6, 2.5, 0.6]))
    if outer_walls:  # walls with an outer side too, as a house has
        parts.append(trimesh.creation.box(extents=[4.4, 2.9, 4.4]))
    return trimesh.util.concatenate(parts)


def _open_top_box():
    """A box of solid walls with no lid (y up)."""
    import trimesh

    def slab(extents, at):
        box = trimesh.creation.box(extents=extents)
        box.apply_translation(at)
        return box

    return trimesh.util.concatenate([slab([1, 0.1, 1], [0, -0.45, 0]), slab([0.1, 1, 1], [-0.45, 0, 0]),
                                     slab([0.1, 1, 1], [0.45, 0, 0]), slab([1, 1, 0.1], [0, 0, -0.45]),
                                     slab([1, 1, 0.1], [0, 0, 0.45])])


def _roofless_room():
    """Four one-sided walls and a floor, facing in, with no ceiling."""
    import trimesh

    room = trimesh.creation.box(extents=[4, 2.5, 4])
    room.invert()
    room.update_faces(~(room.face_normals[:, 1] < -0.9))  # the ceiling faces down, into the room
    return room


def _holed(kind):
    """Objects with a hole through them, modelled along z."""
    import trimesh

    if kind == "torus":
        return trimesh.creation.torus(1.0, 0.3)
    if kind == "washer":  # thick: its bore surrounds a probe in most directions
        return trimesh.creation.annulus(r_min=0.4, r_max=1.0, height=1.5)
    if kind == "pipe":  # long and thin-walled, with a bore narrower than the spread probe rays find
        return trimesh.creation.annulus(r_min=0.2, r_max=0.3, height=8.0)
    return trimesh.creation.annulus(r_min=0.5, r_max=1.0, height=1.6, sections=6)  # a hexagonal nut


@pytest.mark.parametrize("kind", ["torus", "washer", "pipe", "nut"])
@pytest.mark.parametrize("up", ["y", "z"])
def test_an_object_with_a_hole_is_not_a_room(tmp_path, kind, up):
    _holed(kind).export(tmp_path / f"{kind}.ply")
    scene = load_scene(scene_from_mesh(tmp_path / f"{kind}.ply", tmp_path / f"{kind}.xml", up=up))
    assert scene.interior is False, scene.interior_reason
    if kind != "torus":  # a torus's hole is too open to surround a probe
        assert "hole through it" in scene.interior_reason


@pytest.mark.parametrize("name,mesh,interior", [("cup", _cup, False), ("vase", lambda: _cup(0.2), False),
                                                ("open_top_box", _open_top_box, False),
                                                ("roofless_room", _roofless_room, True),
                                                ("room_with_pillar", _room, True),
                                                ("house", lambda: _room(False, True), True),
                                                ("open_front_room", _open_front_room, True)])
def test_rooms_are_told_from_hollow_objects(tmp_path, name, mesh, interior):
    mesh().export(tmp_path / f"{name}.obj")
    up = "z" if name in ("cup", "vase") else "y"
    scene = load_scene(scene_from_mesh(tmp_path / f"{name}.obj", tmp_path / f"{name}.xml", up=up))
    assert scene.interior is interior


def test_simple_scene_is_z_up(shared_data):
    assert np.allclose(load_scene(shared_data / "mitsuba/simple/scene.xml").up, [0, 0, 1])


def test_content_hash_follows_referenced_files(tmp_path, shared_data):
    a = scene_from_mesh(shared_data / "meshes" / "suzanne.obj", tmp_path / "a" / "s.xml")
    b = scene_from_mesh(shared_data / "meshes" / "suzanne.obj", tmp_path / "b" / "s.xml", color=(0.1, 0.1, 0.1))
    h1 = load_scene(a).content_hash
    assert h1 == load_scene(a).content_hash
    assert h1 != load_scene(b).content_hash
    (tmp_path / "a" / "suzanne.ply").write_bytes((tmp_path / "b" / "suzanne.ply").read_bytes()[:-12] + b"\0" * 12)
    assert load_scene(a).content_hash != h1


def test_content_hash_follows_files_named_through_parameters(tmp_path, shared_data):
    import shutil

    shutil.copyfile(shared_data / "meshes" / "suzanne.obj", tmp_path / "a.obj")
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><default name="m" value="a.obj"/>'
                   '<emitter type="constant"/><shape type="obj"><string name="filename" value="$m"/></shape></scene>')
    h1 = load_scene(xml).content_hash
    with open(tmp_path / "a.obj", "a") as f:
        f.write("# edited\n")  # the same bounds and renders: only the hash can tell
    assert load_scene(xml).content_hash != h1


def test_content_hash_follows_files_where_mitsuba_finds_them(tmp_path, shared_data):
    """Through a <path> folder, a spectrum's filename attribute, and an include's names, which
    resolve against the top-level file's folder (not the included file's)."""
    import shutil

    for folder in ("assets", "frag"):
        (tmp_path / folder).mkdir()
    shutil.copyfile(shared_data / "meshes" / "suzanne.obj", tmp_path / "assets" / "a.obj")
    shutil.copyfile(shared_data / "meshes" / "suzanne.obj", tmp_path / "b.obj")
    shutil.copyfile(shared_data / "meshes" / "cow.obj", tmp_path / "frag" / "b.obj")  # not what Mitsuba loads
    (tmp_path / "assets" / "white.spd").write_text("400 1\n700 1\n")
    (tmp_path / "frag" / "part.xml").write_text('<scene version="3.0.0"><shape type="obj">'
                                                '<string name="filename" value="b.obj"/></shape></scene>')
    xml = tmp_path / "s.xml"
    xml.write_text('<scene version="3.0.0"><path value="assets"/><include filename="frag/part.xml"/>'
                   '<emitter type="constant"><spectrum name="radiance" filename="white.spd"/></emitter>'
                   '<shape type="obj"><string name="filename" value="a.obj"/></shape></scene>')
    scene = load_scene(xml)
    assert sorted(s.vertex_count() for s in scene.mi_scene.shapes()) == [507, 507]  # suzanne twice, no cow
    for edited in ("assets/a.obj", "assets/white.spd", "b.obj"):
        before = load_scene(xml).content_hash
        with open(tmp_path / edited, "a") as f:
            f.write("# edited\n")
        assert load_scene(xml).content_hash != before, edited


def test_interior_free_space(shared_data):
    scene = load_scene(shared_data / "mitsuba/cbox/cbox.xml")
    inside_box = [185.0, 80.0, 169.0]
    assert scene.free_space(np.array([scene.center, inside_box])).tolist() == [True, False]


def test_authoring_never_replaces_a_file_with_other_content(tmp_path, shared_data):
    out = tmp_path / "out"
    out.mkdir()
    (out / "suzanne.ply").write_bytes(b"the user's own file")
    mesh = shared_data / "meshes" / "suzanne.obj"
    a = scene_from_mesh(mesh, out / "a.xml")
    assert (out / "suzanne.ply").read_bytes() == b"the user's own file"
    assert 'value="suzanne_scene.ply"' in a.read_text()
    # A second scene of the same mesh turned another way keeps the first one whole.
    a_mesh = (out / "suzanne_scene.ply").read_bytes()
    b = scene_from_mesh(mesh, out / "b.xml", up="z")
    assert 'value="suzanne_scene2.ply"' in b.read_text() and (out / "suzanne_scene.ply").read_bytes() == a_mesh
    # Authored again as it was, a scene finds its own file and leaves it untouched.
    mtime = (out / "suzanne_scene.ply").stat().st_mtime_ns
    assert 'value="suzanne_scene.ply"' in scene_from_mesh(mesh, out / "c.xml").read_text()
    assert (out / "suzanne_scene.ply").stat().st_mtime_ns == mtime
    assert sorted(f.name for f in out.iterdir()) == ["a.xml", "b.xml", "c.xml", "suzanne.ply", "suzanne_scene.ply",
                                                     "suzanne_scene2.ply"]
    extent = [load_scene(xml).bbox_max - load_scene(xml).bbox_min for xml in (a, b)]
    assert np.allclose(extent[0][[0, 2, 1]], extent[1], atol=1e-4) and not np.allclose(extent[0], extent[1], atol=1e-2)


def test_authored_again_a_scene_replaces_the_files_only_it_names(tmp_path, shared_data):
    mesh = shared_data / "meshes" / "suzanne.obj"
    scene_from_mesh(mesh, tmp_path / "s.xml")
    z_up = scene_from_mesh(mesh, tmp_path / "s.xml", up="z")
    assert 'value="suzanne.ply"' in z_up.read_text()
    assert sorted(f.name for f in tmp_path.iterdir()) == ["s.xml", "suzanne.ply"]  # no file left behind
    # Once another scene names it too, it is kept.
    turned = (tmp_path / "suzanne.ply").read_bytes()
    scene_from_mesh(mesh, tmp_path / "t.xml", up="z")
    scene_from_mesh(mesh, tmp_path / "t.xml")
    assert (tmp_path / "suzanne.ply").read_bytes() == turned and "suzanne_scene.ply" in (tmp_path / "t.xml").read_text()


@pytest.mark.parametrize("options", ["", "-s 1 1 1 "])  # trimesh reads the image only without options
def test_a_meshs_material_texture_comes_before_an_image_named_like_it(tmp_path, shared_data, options):
    from PIL import Image

    obj = tmp_path / "m.obj"
    obj.write_bytes(b"mtllib m.mtl\nusemtl mat\n" + (shared_data / "meshes" / "spot.obj").read_bytes())
    (tmp_path / "m.mtl").write_text(f"newmtl mat\nKd 1 1 1\nmap_Kd {options}tex/diffuse.jpg\n")
    (tmp_path / "tex").mkdir()
    Image.new("RGB", (16, 16), (10, 200, 10)).save(tmp_path / "tex" / "diffuse.jpg")
    Image.new("RGB", (16, 16), (200, 10, 10)).save(tmp_path / "m.png")
    xml = scene_from_mesh(obj, tmp_path / "out" / "m.xml")
    # The material's own file, copied as it is (not re-encoded).
    assert 'value="m_texture.jpg"' in xml.read_text()
    assert (tmp_path / "out" / "m_texture.jpg").read_bytes() == (tmp_path / "tex" / "diffuse.jpg").read_bytes()
    # Without a material's image (a blank map_Kd names none), the image named like the mesh.
    (tmp_path / "m.mtl").write_bytes(b"newmtl mat\nKd 1 1 1\nmap_Kd  \r\n")
    xml = scene_from_mesh(obj, tmp_path / "out2" / "m.xml")
    assert (tmp_path / "out2" / "m_texture.png").read_bytes() == (tmp_path / "m.png").read_bytes()


def test_a_material_texture_left_out_is_named_in_a_warning(tmp_path, shared_data):
    import warnings

    def authored(mesh, mtl_texture, **options):
        """The warnings of authoring ``mesh`` with one material naming ``mtl_texture``, and the XML's text."""
        obj = tmp_path / "m.obj"
        obj.write_bytes(b"mtllib m.mtl\nusemtl mat\n" + (shared_data / "meshes" / mesh).read_bytes())
        (tmp_path / "m.mtl").write_text(f"newmtl mat\nKd 0.8 0.2 0.2\nmap_Kd {mtl_texture}\n")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            xml = scene_from_mesh(obj, tmp_path / "out" / "m.xml", **options)
        return [str(w.message) for w in caught], xml.read_text()

    missing, text = authored("spot.obj", "tex/gone.png")
    assert len(missing) == 1 and f"{tmp_path / 'tex' / 'gone.png'}" in missing[0] and "is not a file" in missing[0]
    assert 'value="0.8 0.2 0.2"' in text  # the material's flat colour, as the warning says
    (tmp_path / "broken.png").write_text("not an image")
    assert "is not an image Mitsuba can read" in authored("spot.obj", "broken.png")[0][0]
    shutil.copyfile(shared_data / "meshes" / "spot_texture.png", tmp_path / "tex.png")
    assert "no texture coordinates" in authored("suzanne.obj", "tex.png")[0][0]
    # No warning where the texture is used, or where textures were turned off.
    used, text = authored("spot.obj", "tex.png")
    assert used == [] and "m_texture.png" in text
    assert authored("spot.obj", "tex/gone.png", texture=False)[0] == []


@pytest.mark.parametrize("what", ["washer", "cbox"])
def test_the_automatic_rig_says_which_and_why(tmp_path, shared_data, what):
    from click.testing import CliRunner

    from mitsuba_active.cli import main

    if what == "washer":
        _holed("washer").export(tmp_path / "washer.ply")
        xml = scene_from_mesh(tmp_path / "washer.ply", tmp_path / "washer.xml", up="z")
    else:
        xml = shared_data / "mitsuba/cbox/cbox.xml"
    result = CliRunner().invoke(main, ["render", str(xml), "-o", str(tmp_path / "views"), "--views", "1",
                                       "--candidates", "2", "--heldout", "1", "--resolution", "8", "--spp", "1"])
    assert result.exit_code == 0, result.output
    notes = [ln for ln in result.output.splitlines() if ln.startswith("note: rig ")]
    expected = ("note: rig sphere, as washer.xml is an object with a hole through it" if what == "washer" else
                "note: rig interior, as cbox.xml is a room seen from inside")
    assert len(notes) == 1 and notes[0].startswith(expected), result.output
    assert notes[0].endswith("--rig hemisphere or interior" if what == "washer" else "--rig sphere or hemisphere")


def _airplane():
    """A Z-up airplane on landing gear: a fuselage along y, wings across x."""
    import trimesh

    fuselage = trimesh.creation.cylinder(0.08, 1.0)
    fuselage.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    parts = [fuselage, trimesh.creation.box([1.0, 0.2, 0.03])]
    for extents, at in (([0.02, 0.15, 0.2], [0, -0.45, 0.12]), ([0.35, 0.1, 0.02], [0, -0.45, 0.02])):
        parts.append(trimesh.creation.box(extents))
        parts[-1].apply_translation(at)
    for at in ((0.15, 0.05, -0.1), (-0.15, 0.05, -0.1), (0, 0.4, -0.1)):
        parts.append(trimesh.creation.cylinder(0.03, 0.05))
        parts[-1].apply_translation(at)
    return trimesh.util.concatenate(parts)


@pytest.mark.parametrize("mesh,taken", [("airplane", "z"), ("suzanne", "y"), ("stanford-bunny", "y")])
def test_the_up_axis_is_taken_from_a_flat_base_and_noted_otherwise(tmp_path, shared_data, mesh, taken):
    from click.testing import CliRunner

    from mitsuba_active.cli import main
    from mitsuba_active.scene import authoring_notes

    if mesh == "airplane":
        _airplane().export(tmp_path / "airplane.ply")
        path = tmp_path / "airplane.ply"
    else:
        path = shared_data / "meshes" / f"{mesh}.obj"
    result = CliRunner().invoke(main, ["scene", str(path), "-o", str(tmp_path / "auto" / "s.xml")])
    assert result.exit_code == 0, result.output
    notes = authoring_notes(tmp_path / "auto" / "s.xml")
    assert [ln for ln in result.output.splitlines() if ln.startswith("note:")] == notes
    if mesh == "airplane":  # Y-up in the scene: its height, the shortest side, is along y
        assert notes == ["note: airplane.ply rests on a flat base across its z axis, so it was taken as Z-up "
                         "(--up y keeps its axes)"]
        scene = load_scene(tmp_path / "auto" / "s.xml")
        extents = scene.bbox_max - scene.bbox_min
        assert extents[1] == extents.min()
    elif mesh == "suzanne":  # no flat base: y, said
        assert notes == ["note: took y as the up axis of suzanne.obj, whose shape shows none (--up z if it is Z-up)"]
    else:  # the bunny sits on a flat cut: nothing to say
        assert notes == []
    given = CliRunner().invoke(main, ["scene", str(path), "-o", str(tmp_path / "given" / "s.xml"), "--up", taken])
    assert given.exit_code == 0 and "note:" not in given.output
    ply = f"{path.stem}.ply"
    assert (tmp_path / "given" / ply).read_bytes() == (tmp_path / "auto" / ply).read_bytes()  # the same axes


def test_the_default_look_is_sunlit_clay(tmp_path, shared_data):
    from mitsuba_active.scene import SceneOptions

    text = scene_from_mesh(shared_data / "meshes" / "suzanne.obj", tmp_path / "a" / "s.xml").read_text()
    assert 'type="directional"' in text
    assert f'<emitter type="constant"><rgb name="radiance" value="{SceneOptions.env_radiance:g}"/>' in text
    assert f'value="{" ".join(f"{c:g}" for c in DEFAULT_COLOR)}"' in text
    assert 'type="directional"' not in scene_from_mesh(shared_data / "meshes" / "suzanne.obj",
                                                       tmp_path / "b" / "s.xml", sun=False).read_text()
    # Shaded: the sunlit top of a ball is brighter than its underside, and well below the white behind it.
    import trimesh

    from mitsuba_active.cameras import Camera, look_at

    trimesh.creation.icosphere(3).export(tmp_path / "ball.ply")
    scene = load_scene(scene_from_mesh(tmp_path / "ball.ply", tmp_path / "c" / "s.xml"))
    image = np.array(mi.render(scene.mi_scene, sensor=Camera(look_at([0, 0, 3], [0, 0, 0]), fov=30.0, width=32,
                                                                height=32).sensor(16))).mean(axis=2)
    top, bottom, corner = image[9, 16], image[23, 16], image[0, 0]
    assert top > 1.4 * bottom and abs(corner - SceneOptions.env_radiance) < 0.02 and top < corner - 0.3


def test_a_missing_material_file_is_named_in_a_warning(tmp_path, shared_data):
    obj = tmp_path / "m.obj"
    obj.write_text("mtllib gone.mtl\n" + (shared_data / "meshes" / "suzanne.obj").read_text())
    with pytest.warns(UserWarning, match=f"the material file {tmp_path / 'gone.mtl'} named by {obj} is not a file"):
        scene_from_mesh(obj, tmp_path / "s.xml")
