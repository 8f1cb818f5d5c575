"""Every kind of bad input: one line on stderr, exit code 2, no traceback, nothing half-written.
(A machine the package cannot run on stops the import itself: one line, exit code 1.)"""

import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mitsuba_active.cli import main
from mitsuba_active.errors import UserError
from mitsuba_active.scene import load_scene


def run_cli(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    return result.exit_code, result.output


def assert_one_line_error(code, output, needle):
    assert code == 2, output
    lines = [ln for ln in output.splitlines() if ln.strip() and "it/s" not in ln and "%|" not in ln]
    assert len(lines) == 1, output
    assert lines[0].startswith("mitsuba-active: error:") and needle in lines[0], output
    assert "Traceback" not in output


@pytest.fixture()
def out(tmp_path):
    return tmp_path / "out"


def _assert_nothing_written(path):
    assert not path.exists() or not any(path.iterdir()), list(path.iterdir())


def test_missing_mesh(tmp_path, out):
    code, text = run_cli("scene", tmp_path / "nope.obj", "-o", out / "s.xml")
    assert_one_line_error(code, text, "not found")
    _assert_nothing_written(out)


def test_unreadable_mesh(tmp_path, out):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\ngarbage")
    code, text = run_cli("scene", bad, "-o", out / "s.xml")
    assert code == 2 and "Traceback" not in text
    _assert_nothing_written(out)


def test_a_texture_and_no_texture_together_are_refused(tmp_path, out, shared_data):
    code, text = run_cli("scene", shared_data / "meshes" / "spot.obj", "-o", out / "s.xml",
                         "--texture", shared_data / "meshes" / "spot_texture.png", "--no-texture")
    assert_one_line_error(code, text, "not both")
    _assert_nothing_written(out)


@pytest.mark.parametrize("content,needle", [
    ("# no geometry at all\n", "no triangles"),
    ("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n", "degenerate"),
    # trimesh merges vertices closer than 1e-8: a mesh that small loses its triangles.
    ("v 0 0 0\nv 2e-9 0 0\nv 0 2e-9 0\nf 1 2 3\n", "spans only 2e-09 units, too small for trimesh"),
    ("v 0 0 0\nv 1e-7 0 0\nv 2e-7 0 0\nf 1 2 3\n", "is degenerate"),  # as small, but without area to lose
    # trimesh drops a NaN vertex's faces on its own: the mesh would lose them unsaid.
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 1\nf 1 2 3\nf 1 2 4\n", "non-finite vertex coordinates"),
    ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "non-finite vertex coordinates"),  # its one triangle, not none
])
def test_empty_and_degenerate_meshes(tmp_path, out, content, needle):
    mesh = tmp_path / "m.obj"
    mesh.write_text(content)
    code, text = run_cli("scene", mesh, "-o", out / "s.xml")
    assert_one_line_error(code, text, needle)
    _assert_nothing_written(out)


def test_malformed_xml(tmp_path, out):
    xml = tmp_path / "broken.xml"
    xml.write_text("<scene version='3.0.0'><shape type='sphere'>")
    code, text = run_cli("render", xml, "-o", out)
    assert_one_line_error(code, text, "malformed XML")
    _assert_nothing_written(out)


def test_xml_nested_past_mitsubas_parser_is_malformed(tmp_path, out):
    """Mitsuba's parser recurses: a scene nested thousands of levels deep would crash it."""
    xml = tmp_path / "deep.xml"
    n = 10_000
    xml.write_text("<scene version='3.0.0'><shape type='sphere'/>" + "<emitter type='constant'>" * n
                   + "</emitter>" * n + "</scene>")
    code, text = run_cli("render", xml, "-o", out)
    assert_one_line_error(code, text, "deep.xml: elements nested more than 1000 deep")
    _assert_nothing_written(out)


def test_xml_mitsuba_rejects(tmp_path, out):
    xml = tmp_path / "odd.xml"
    xml.write_text("<scene version='3.0.0'><shape type='no_such_plugin'/></scene>")
    code, text = run_cli("render", xml, "-o", out)
    assert_one_line_error(code, text, "Mitsuba cannot load")
    _assert_nothing_written(out)


def test_scene_without_shapes(tmp_path, out):
    xml = tmp_path / "empty.xml"
    xml.write_text("<scene version='3.0.0'><emitter type='constant'/></scene>")
    code, text = run_cli("render", xml, "-o", out)
    assert_one_line_error(code, text, "no shapes")
    _assert_nothing_written(out)


def test_zero_resolution(spot_xml, out):
    code, text = run_cli("render", spot_xml, "-o", out, "--resolution", "0")
    assert_one_line_error(code, text, "resolution")
    _assert_nothing_written(out)


def test_real_process_exit_code_and_stderr(tmp_path):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    proc = subprocess.run([sys.executable, "-m", "mitsuba_active", "scene", str(tmp_path / "x.obj"), "-o",
                           str(tmp_path / "o.xml")], capture_output=True, text=True, env=env)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "mitsuba-active: error:" in proc.stderr
    assert not (tmp_path / "o.xml").exists()


#: The LLVM checks concern the CPU variant, also where the suite runs under cuda_ad_rgb.
LLVM_VARIANT = {"MITSUBA_ACTIVE_VARIANT": "llvm_ad_rgb"}


def test_missing_llvm_is_one_line_with_the_fix(tmp_path):
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "libLLVM-nothing.so"), **LLVM_VARIANT)
    for command in (["-c", "import mitsuba_active"], ["-m", "mitsuba_active", "plan", "--help"]):
        proc = subprocess.run([sys.executable, *command], capture_output=True, text=True, env=env)
        assert proc.returncode == 1 and proc.stdout == ""
        assert proc.stderr.strip().count("\n") == 0 and "apt-get install libllvm19" in proc.stderr


def test_missing_llvm_is_an_import_error_a_pipeline_can_catch(tmp_path):
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(tmp_path / "libLLVM-nothing.so"), **LLVM_VARIANT)
    code = ("try:\n    import mitsuba_active\nexcept ImportError as exc:\n    print('without:', exc)\n"
            "raise ValueError('the pipeline goes on')")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert proc.stdout.startswith("without: ") and "libllvm19" in proc.stdout
    # Other exceptions keep their tracebacks.
    assert "Traceback" in proc.stderr and "ValueError: the pipeline goes on" in proc.stderr


def test_a_pipeline_variant_that_cannot_run_fields_is_switched_with_a_warning():
    code = ("import warnings, mitsuba as mi\nmi.set_variant('scalar_rgb')\n"
            "with warnings.catch_warnings(record=True) as caught:\n    warnings.simplefilter('always')\n"
            "    import mitsuba_active\n"
            "print(mi.variant(), '|', '; '.join(f'{w.filename}:{w.lineno}: {w.message}' for w in caught))")
    env = dict(os.environ, **LLVM_VARIANT)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    variant, _, warned = proc.stdout.strip().partition(" | ")
    assert proc.returncode == 0 and variant == "llvm_ad_rgb"
    # Shown at the pipeline's own import line, not inside the package.
    assert "<string>:5: mitsuba-active switched Mitsuba from variant 'scalar_rgb' to 'llvm_ad_rgb'" in warned


def test_a_variant_switched_after_import_is_refused_before_rendering(tmp_path):
    # A spectral render would land in the ground-truth cache under an RGB render's key.
    xml = tmp_path / "ball.xml"
    xml.write_text('<scene version="3.0.0"><shape type="sphere"/><emitter type="constant"/></scene>')
    code = (f"import mitsuba_active, mitsuba as mi\nfrom mitsuba_active.env import SceneSource\n"
            f"from mitsuba_active.field import Ensemble\n"
            f"src = SceneSource.from_xml({str(xml)!r}, n_candidates=2, n_heldout=1, resolution=8, spp=1, "
            f"cache_dir={str(tmp_path / 'cache')!r})\n"
            "mi.set_variant('llvm_ad_spectral')\n"
            "for make in (lambda: src.candidate_view(0), lambda: Ensemble([-1] * 3, [1] * 3),\n"
            f"             lambda: SceneSource.from_xml({str(xml)!r}, n_candidates=2, n_heldout=1)):\n"
            "    try:\n        make()\n    except mitsuba_active.UserError as exc:\n        print(exc)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=dict(os.environ, **LLVM_VARIANT))
    lines = proc.stdout.splitlines()
    assert proc.returncode == 0 and len(lines) == 3, proc.stderr
    assert lines[0].startswith("rendering ground truth needs Mitsuba variant llvm_ad_rgb or cuda_ad_rgb")
    assert lines[1].startswith("Ensemble needs") and "'llvm_ad_spectral' is set" in lines[1]
    assert lines[2].startswith("loading a scene needs") and "'llvm_ad_spectral' is set" in lines[2]
    assert not (tmp_path / "cache").exists()


def test_gpu_variant_without_a_gpu_says_so():
    import drjit as dr

    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("this machine has a GPU")
    env = dict(os.environ, MITSUBA_ACTIVE_VARIANT="cuda_ad_rgb")
    proc = subprocess.run([sys.executable, "-m", "mitsuba_active", "--version"], capture_output=True, text=True,
                          env=env)
    assert proc.returncode == 1 and proc.stderr.strip().count("\n") == 0
    assert "needs an NVIDIA GPU" in proc.stderr and "unset MITSUBA_ACTIVE_VARIANT" in proc.stderr


def test_an_empty_variant_setting_counts_as_unset():
    code = "import mitsuba_active, mitsuba as mi; print(mi.variant())"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=dict(os.environ, MITSUBA_ACTIVE_VARIANT=""))
    assert proc.returncode == 0 and proc.stdout.strip() == "llvm_ad_rgb", proc.stderr


def test_llvm_search_rejects_old_versions(monkeypatch, tmp_path):
    from mitsuba_active import variant

    for name in ("libLLVM-14.so.1", "libLLVM-15.so"):
        (tmp_path / name).write_bytes(b"")
    monkeypatch.setattr(variant, "LLVM_SEARCH_GLOBS", (str(tmp_path / "libLLVM*.so*"),))
    assert variant.find_llvm() is None
    (tmp_path / "libLLVMSPIRVLib.so.20.1").write_bytes(b"")  # a companion library, not LLVM itself
    assert variant.find_llvm() is None
    (tmp_path / "libLLVM.so.19.1").write_bytes(b"")
    assert variant.find_llvm().endswith("libLLVM.so.19.1")


def test_scene_never_overwrites_the_input_mesh(tmp_path, shared_data):
    mesh = tmp_path / "suzanne.ply"
    import trimesh

    trimesh.load(shared_data / "meshes" / "suzanne.obj", force="mesh").export(mesh)
    before = mesh.read_bytes()
    code, text = run_cli("scene", mesh, "-o", tmp_path / "suzanne.xml")
    assert code == 0, text
    assert mesh.read_bytes() == before and (tmp_path / "suzanne_scene.ply").is_file()


def test_texture_without_uvs(tmp_path, shared_data, out):
    code, text = run_cli("scene", shared_data / "meshes" / "teapot.obj", "-o", out / "t.xml", "--texture",
                         shared_data / "meshes" / "spot_texture.png")
    assert_one_line_error(code, text, "texture coordinates")
    _assert_nothing_written(out)


@pytest.mark.parametrize("texture,needle", [("garbage.png", "not an image"), ("/dev/null", "not a file")])
def test_texture_that_is_not_an_image(tmp_path, shared_data, out, texture, needle):
    (tmp_path / "garbage.png").write_text("garbage")
    code, text = run_cli("scene", shared_data / "meshes" / "spot.obj", "-o", out / "s.xml", "--texture",
                         tmp_path / texture if texture == "garbage.png" else texture)
    assert_one_line_error(code, text, needle)
    assert not out.exists()


def test_a_scene_mitsuba_refuses_leaves_no_folders(tmp_path, shared_data, monkeypatch):
    import mitsuba_active.scene.authoring as authoring

    def refuse(path, **params):
        raise UserError(f"Mitsuba cannot load {path}")

    monkeypatch.setattr(authoring, "load_mitsuba", refuse)
    with pytest.raises(UserError, match="cannot load"):
        authoring.scene_from_mesh(shared_data / "meshes" / "spot.obj", tmp_path / "a" / "b" / "s.xml")
    assert list(tmp_path.iterdir()) == []


def test_zero_field_of_view(spot_xml, out):
    code, text = run_cli("render", spot_xml, "-o", out, "--fov", "0")
    assert_one_line_error(code, text, "field of view")
    _assert_nothing_written(out)


def test_old_llvm_named_by_the_user_is_refused(tmp_path):
    old = tmp_path / "libLLVM-15.so"
    old.write_bytes(b"")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(old), **LLVM_VARIANT)
    proc = subprocess.run([sys.executable, "-c", "import mitsuba_active"], capture_output=True, text=True, env=env)
    assert proc.returncode == 1 and "LLVM 15" in proc.stderr and "libllvm19" in proc.stderr
    # A file that is no library at all: one line with the fix, not Dr.Jit's loader errors.
    text = tmp_path / "libLLVM.so"
    text.write_text("not a library\n")
    env["DRJIT_LIBLLVM_PATH"] = str(text)
    proc = subprocess.run([sys.executable, "-c", "import mitsuba_active"], capture_output=True, text=True, env=env)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1, proc.stderr
    assert "is not a shared library" in proc.stderr and "libllvm19" in proc.stderr


@pytest.mark.parametrize("script, args, message", [
    ("train_throughput.py", ["--set", "speed=3"], "expected OPTION=VALUE with a FieldConfig option"),
    ("train_throughput.py", ["--set", "occupancy_resolution=32"], "leave occupancy_resolution at 0"),
    ("fit_quality.py", ["--set", "n_levels=two"], "FieldConfig.n_levels must be of type int"),
    ("disagreement.py", ["--views", "2"], "needs --views >= 3, --members >= 2 and --steps-per-view >= 1"),
])
def test_benchmark_scripts_refuse_bad_field_options(script, args, message):
    from tests.conftest import REPO

    proc = subprocess.run([sys.executable, str(REPO / "benchmarks" / script), *args],
                          capture_output=True, text=True, cwd=REPO)
    assert proc.returncode == 2 and message in proc.stderr
    # argparse's usage line, then the error as the one last line; no traceback.
    assert "Traceback" not in proc.stderr and message in proc.stderr.strip().splitlines()[-1]


@pytest.mark.parametrize("options, message", [
    (dict(lr=-0.01), "lr must be > 0"),
    (dict(lr=float("nan")), "lr must be a finite number"),
    (dict(lr="fast"), "lr must be a finite number"),
    (dict(n_levels=True), "n_levels must be a finite number"),
    (dict(beta_2=1.0), "beta_1 and beta_2 must be in"),
    (dict(init_scale=-1.0), "init_scale must be >= 0"),
    (dict(n_levels=2.5), "n_levels must be a whole number"),
    (dict(batch_rays=10**400), "batch_rays must be a finite number"),
    # Values that would only exhaust memory or overflow the grid's coordinates.
    (dict(n_samples=10**8), "batch_rays x n_samples = 409600000000 samples per batch, more than 16777216"),
    (dict(render_batch=10**6), "render_batch x n_samples"),
    (dict(n_levels=100), "n_levels must be at most 16"),
    (dict(per_level_scale=1e300), "the finest level would have more than 65536 cells per axis"),
    (dict(bbox_padding=1e30), "bbox_padding must be at most 1"),
    (dict(view_degree=3), "view_degree must be in \\[0, 2\\]"),
    (dict(view_degree=1, view_resolution=0), "view_resolution in \\[1, 256\\]"),
])
def test_field_options_out_of_range(options, message):
    from mitsuba_active.field import FieldConfig

    with pytest.raises(UserError, match=message):
        FieldConfig(**options)


@pytest.mark.parametrize("settings, message", [
    (dict(budget=4.5), "budget must be a whole number"),
    (dict(initial_views=True), "initial_views must be a whole number"),
    (dict(eval_views=4), "eval_views must be a list"),
    (dict(fov="wide"), "fov must be a number"),
    (dict(seed=-1), "the seed must be in"),
    (dict(field=3), "field must be a table"),
    (dict(eval_views=[0, 5]), "eval_views must be a list of positive view counts"),
    # Far beyond any use: refused before anything runs, not a traceback or an endless run.
    (dict(eval_steps=10**20), "a training may take at most 10,000,000 steps"),
    (dict(steps_per_view=10**6), r"initial_steps \+ steps_per_view x budget = 20,000,200"),
    (dict(rays_per_candidate=10**20), r"rays per candidate must be in \[1, 65536\]"),
    (dict(ensemble=1000), "the ensemble needs between 1 and 64 members"),
    (dict(spp=10**11), r"samples per pixel must be in \[1, 65536\]"),
])
def test_run_settings_of_the_wrong_type(settings, message):
    from mitsuba_active.run import RunConfig

    with pytest.raises(UserError, match=message):
        RunConfig(**settings).validate()


@pytest.mark.parametrize("options, message", [
    (dict(color="red"), "color must be three numbers"),
    (dict(color=[1.5, 0, 0]), "color must be three numbers"),
    (dict(point_lights=2.5), "point_lights must be a whole number"),
    (dict(point_lights=99), r"point_lights must be a whole number in \[0, 16\], got 99"),
    (dict(sun="yes"), "sun must be true or false"),
    (dict(up="x"), "the up axis must be"),
    (dict(texture=True), "texture must be an image path"),
    (dict(env_radiance=10**400), "env_radiance must be a number"),
])
def test_scene_options_of_the_wrong_type(options, message, tmp_path, shared_data):
    from mitsuba_active.bench import load_suite
    from mitsuba_active.scene import scene_from_mesh

    with pytest.raises(UserError, match=message):
        scene_from_mesh(shared_data / "meshes" / "suzanne.obj", tmp_path / "s" / "s.xml", **options)
    assert not (tmp_path / "s").exists()
    suite = tmp_path / "suite.toml"
    toml = {k: (repr(v).lower() if isinstance(v, bool) else repr(v)) for k, v in options.items()}
    suite.write_text("[[scenes]]\nname = 'a'\nmesh = 'x.obj'\n" + "".join(f"{k} = {v}\n" for k, v in toml.items()))
    with pytest.raises(UserError, match=f"scene 'a': {message}"):
        load_suite(suite)


def test_a_misspelt_scene_option_is_named(tmp_path, shared_data):
    from mitsuba_active.scene import scene_from_mesh

    with pytest.raises(UserError, match="unknown scene option colour; the options of SceneOptions are: .*color"):
        scene_from_mesh(shared_data / "meshes" / "suzanne.obj", tmp_path / "s" / "s.xml", colour=(1, 0, 0))
    assert not (tmp_path / "s").exists()


def test_a_path_depth_mitsuba_cannot_read_is_refused():
    from mitsuba_active.scene import SceneOptions

    with pytest.raises(UserError, match=r"max_depth must be a whole number in \[1, 1024\], got 1099511627776"):
        SceneOptions(max_depth=2**40)


def test_a_mesh_inside_the_run_folder_is_kept(tmp_path):
    import hashlib

    import trimesh

    mesh = tmp_path / "run" / "scene" / "ball.ply"
    mesh.parent.mkdir(parents=True)
    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    digest = hashlib.sha256(mesh.read_bytes()).hexdigest()
    code, text = run_cli("plan", mesh, "--out", tmp_path / "run", "--resolution", "8", "--spp", "1",
                         "--candidates", "4", "--heldout", "1", "--budget", "2", "--eval-steps", "5",
                         "--planner", "even", "--quiet")
    assert code == 0, text
    assert hashlib.sha256(mesh.read_bytes()).hexdigest() == digest


def test_a_run_folder_is_never_given_another_scene(tmp_path):
    import hashlib

    import trimesh

    trimesh.creation.icosphere(subdivisions=2).export(tmp_path / "ball.ply")
    (tmp_path / "other").mkdir()
    trimesh.creation.box().export(tmp_path / "other" / "ball.ply")
    out = tmp_path / "run"
    tiny = ["--resolution", "8", "--spp", "1", "--candidates", "4", "--heldout", "1", "--budget", "2",
            "--eval-steps", "5", "--steps-per-view", "2", "--planner", "even", "--quiet", "--out", out]
    code, text = run_cli("plan", tmp_path / "ball.ply", *tiny)
    assert code == 0, text

    def files():
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in (out / "scene").iterdir()}

    before = files()
    for mesh in (tmp_path / "other" / "ball.ply", tmp_path / "ball.ply"):
        if mesh.parent == tmp_path:  # the same mesh again: the finished run is reported as it is
            code, text = run_cli("plan", mesh, *tiny)
            assert code == 0 and "already complete" in text, text
        else:  # another mesh of the same name: refused, nothing overwritten
            code, text = run_cli("plan", mesh, *tiny)
            assert_one_line_error(code, text, f"--out {out}: holds a run of another scene")
        assert files() == before


def test_unwritable_cache_is_one_line_and_leaves_no_views(spot_xml, tmp_path, monkeypatch):
    blocker = tmp_path / "afile"
    blocker.write_text("")
    monkeypatch.setenv("MITSUBA_ACTIVE_CACHE", str(blocker / "cache"))
    out = tmp_path / "new" / "views"
    code, text = run_cli("render", spot_xml, "-o", out, "--resolution", "8", "--spp", "1", "--candidates", "2",
                         "--heldout", "1")
    assert_one_line_error(code, text, "MITSUBA_ACTIVE_CACHE")
    assert not (tmp_path / "new").exists()  # nor the parent it made
    # A run that fails after capturing views leaves an existing folder as it was.
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    monkeypatch.setenv("MITSUBA_ACTIVE_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr("mitsuba_active.run.Run._save_record", lambda self: (_ for _ in ()).throw(OSError(28, "full")))
    code, text = run_cli("plan", spot_xml, "--out", out, "--resolution", "8", "--spp", "1", "--candidates", "4",
                         "--heldout", "1", "--budget", "2", "--quiet")
    assert_one_line_error(code, text, "full")
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_a_run_record_that_is_not_one(spot_xml, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    for content in (b"[]", b"\x00\xff not json", b"\xff\xfe"):
        (out / "run.json").write_bytes(content)
        code, text = run_cli("plan", spot_xml, "--out", out, "--resolution", "8", "--spp", "1",
                             "--candidates", "4", "--heldout", "1", "--budget", "2", "--quiet")
        assert_one_line_error(code, text, "run.json")


def test_bench_set_errors_are_one_line(tmp_path):
    from tests.conftest import REPO

    suite = REPO / "benchmarks" / "suites" / "shared.toml"
    for item, needle in (("ensemble=0", "between 1 and 64 members"), ("field.lr=-1", "lr must be > 0"),
                         ("seed=3", "--seeds"), ("ensemble=1", "at least 2 members"),
                         ("eval_views=4", "eval_views must be a list")):
        code, text = run_cli("bench", suite, "--scenes", "spot", "--out", tmp_path / "b", "--set", item)
        assert_one_line_error(code, text, needle)
        assert not (tmp_path / "b").exists()


def test_unwritable_output_is_one_line(tmp_path, shared_data):
    blocker = tmp_path / "afile"
    blocker.write_text("")
    code, text = run_cli("scene", shared_data / "meshes" / "suzanne.obj", "-o", blocker / "x.xml")
    assert_one_line_error(code, text, f"{blocker} is a file, where a folder is needed")
    # Deeper under the file: still the file is named.
    code, text = run_cli("scene", shared_data / "meshes" / "suzanne.obj", "-o", blocker / "a" / "b" / "x.xml")
    assert_one_line_error(code, text, f"{blocker} is a file, where a folder is needed")


def test_plan_bad_numbers_and_names(spot_xml, tmp_path):
    out = tmp_path / "o"
    for args, needle in ([["--distance-weight", "-1"], "distance weight"],
                         [["--distance-weight", "inf"], "distance weight"],
                         [["--candidates", "0"], "candidate view"],
                         # Sizes that would exhaust memory, or Dr.Jit's array sizes, before any progress.
                         [["--resolution", "100000"], "100000x100000 pixels are too large"],
                         [["--candidates", "100000000"], "more than a rig makes"]):
        code, text = run_cli("plan", spot_xml, "--out", out, *args)
        assert_one_line_error(code, text, needle)
        assert not out.exists()
    # Click's own range check: usage text, exit 2, no traceback.
    result = CliRunner().invoke(main, ["plan", str(spot_xml), "--seed", "-1", "--out", str(out)])
    assert result.exit_code == 2 and "--seed" in result.output and "Traceback" not in result.output


def test_a_failed_plan_leaves_no_folder(tmp_path, shared_data):
    # A mesh gets its scene authored into the run folder; the authored scene has
    # one sensor, too few candidates for the budget: the folder goes again.
    out = tmp_path / "o"
    code, text = run_cli("plan", shared_data / "meshes" / "suzanne.obj", "--out", out, "--rig", "xml",
                         "--budget", "2", "--heldout", "1", "--resolution", "8", "--spp", "1", "--quiet")
    assert_one_line_error(code, text, "larger than the number of candidate views (1)")
    assert not out.exists()
    # A folder that was there already keeps what it held, and gets nothing more.
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code, text = run_cli("plan", shared_data / "meshes" / "suzanne.obj", "--out", out, "--rig", "xml",
                         "--budget", "2", "--heldout", "1", "--resolution", "8", "--spp", "1", "--quiet")
    assert_one_line_error(code, text, "larger than the number of candidate views (1)")
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_an_output_that_cannot_be_written_is_named_not_its_temporary_file(spot_xml, tmp_path):
    (tmp_path / "r" / "run.json").mkdir(parents=True)
    code, text = run_cli("plan", spot_xml, "--out", tmp_path / "r", *TINY_PLAN)
    assert_one_line_error(code, text, f"{tmp_path / 'r' / 'run.json'}: Is a directory")
    (tmp_path / "v" / "cameras.json").mkdir(parents=True)
    code, text = run_cli("render", spot_xml, "-o", tmp_path / "v", "--views", "1", "--resolution", "8", "--spp", "1")
    assert_one_line_error(code, text, f"{tmp_path / 'v' / 'cameras.json'}: Is a directory")
    assert [p.name for p in (tmp_path / "v").iterdir()] == ["cameras.json"]


def test_render_needs_a_folder_to_write(spot_xml, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, text = run_cli("render", spot_xml, "-o", "", "--views", "1", "--resolution", "8", "--spp", "1")
    assert_one_line_error(code, text, "-o/--output names no folder")
    assert not list(tmp_path.iterdir())


def test_a_mesh_that_is_not_a_file_is_named_as_such(tmp_path, out):
    os.mkfifo(tmp_path / "pipe.obj")
    (tmp_path / "link.obj").symlink_to(tmp_path / "gone.obj")
    for mesh, needle in (("pipe.obj", "pipe.obj is not a regular file"), ("link.obj", "mesh file not found")):
        code, text = run_cli("scene", tmp_path / mesh, "-o", out / "s.xml")
        assert_one_line_error(code, text, needle)
        code, text = run_cli("plan", tmp_path / mesh, "--out", out)
        assert_one_line_error(code, text, needle)
    _assert_nothing_written(out)


def test_render_and_export_name_the_wrong_kind_of_input(tmp_path, shared_data, out):
    code, text = run_cli("render", shared_data / "meshes" / "cow.obj", "-o", out)
    assert_one_line_error(code, text, "mitsuba-active scene")
    _assert_nothing_written(out)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run.json").write_text('{"format": 1}')
    code, text = run_cli("export", tmp_path / "run")
    assert_one_line_error(code, text, "not a run record")


def test_a_flat_mesh_plans_through(tmp_path):
    """A single quad (no depth) is a valid object: the fields' box gets depth."""
    quad = tmp_path / "quad.obj"
    quad.write_text("v -1 -1 0\nv 1 -1 0\nv 1 1 0\nv -1 1 0\nf 1 2 3 4\n")
    code, text = run_cli("plan", quad, "--planner", "even", "--budget", "3", "--resolution", "16",
                         "--candidates", "8", "--heldout", "2", "--spp", "2", "--eval-views", "2,3",
                         "--eval-steps", "10", "--steps-per-view", "5", "--quiet", "--out", tmp_path / "run")
    assert code == 0, text
    assert "3 views" in text or "3:" in text


def _rectangle_xml(path, scale):
    path.write_text(f'<scene version="3.0.0"><shape type="rectangle"><transform name="to_world">'
                    f'<scale value="{scale}"/></transform></shape><emitter type="constant"/></scene>')
    return path


def test_a_scene_too_large_for_single_precision_is_refused(tmp_path, out):
    code, text = run_cli("render", _rectangle_xml(tmp_path / "huge.xml", "1e30"), "-o", out)
    assert_one_line_error(code, text, "scale it down")
    _assert_nothing_written(out)


def test_cameras_of_a_large_scene_see_all_of_it(tmp_path, shared_data):
    from mitsuba_active.rigs import scene_rigs
    from mitsuba_active.scene import load_scene

    scene = load_scene(_rectangle_xml(tmp_path / "big.xml", "1e6"))
    candidates, heldout = scene_rigs(scene, "sphere", 4, 2)
    for cam in candidates + heldout:
        reach = np.linalg.norm(cam.position - scene.center) + scene.radius
        assert cam.far > reach
    # Scenes of usual sizes (the Cornell box spans ~1000 units) keep the default
    # clip range, and with it their ground truth's cache keys and run records.
    cbox = load_scene(shared_data / "mitsuba" / "cbox" / "cbox.xml")
    for cam in sum(scene_rigs(cbox, "auto", 4, 2), []):
        assert (cam.near, cam.far) == (1e-3, 1e4)


def test_sigterm_stops_plan_like_ctrl_c(tmp_path, spot_xml):
    """``kill`` (SIGTERM) before the first run record: exit 130, one line,
    and the views already written are removed with the folder."""
    import signal
    import time

    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "mitsuba_active", "plan", str(spot_xml), "--resolution", "16",
                             "--candidates", "8", "--heldout", "2", "--spp", "2", "--budget", "4",
                             "--steps-per-view", "1000000", "--quiet", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not list(out.glob("views/*.png")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130 and err.strip().splitlines()[-1] == "mitsuba-active: interrupted", err
    assert not out.exists()


def test_an_interrupt_while_a_render_runs_is_raised_once_the_render_has_ended():
    """Renders run in a helper thread (Mitsuba's own SIGINT handler must not interrupt the
    main thread inside an allocation); the main thread's Ctrl-C waits for the render."""
    import signal
    import threading
    import time

    from mitsuba_active.interrupts import waiting_for

    ended = []

    def render():
        time.sleep(0.5)
        ended.append(threading.current_thread() is not threading.main_thread())
        return "image"

    threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()
    with pytest.raises(KeyboardInterrupt):
        waiting_for(render)
    assert ended == [True]
    assert waiting_for(render) == "image"
    with pytest.raises(ZeroDivisionError):
        waiting_for(lambda: 1 / 0)


def test_an_interrupt_inside_a_late_import_still_exits_130(tmp_path):
    """An interrupt raised within exec() of a string (as dataclasses build their
    methods while a module is imported) must not turn the exit into a SIGINT death."""
    (tmp_path / "interrupted_command.py").write_text(
        "from mitsuba_active.cli.common import one_line_errors\n\n\n@one_line_errors\ndef command():\n"
        "    exec('raise KeyboardInterrupt')\n\n\ncommand()\n")
    proc = subprocess.run([sys.executable, "-m", "interrupted_command"], capture_output=True, text=True,
                          cwd=tmp_path, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 130 and proc.stderr.strip() == "mitsuba-active: interrupted", proc.stderr


def test_an_interrupt_inside_a_drjit_loop_is_one_line_and_exits_130(tmp_path):
    """Dr.Jit re-raises what a loop's body raised as a RuntimeError: a Ctrl-C
    (or SIGTERM) that lands while the renderer traces its ray-marching loop."""
    (tmp_path / "interrupted_loop.py").write_text(
        "from mitsuba_active.cli.common import one_line_errors\nimport drjit as dr, mitsuba as mi\n\n\n"
        "def body(i):\n    raise KeyboardInterrupt\n\n\n@one_line_errors\ndef command():\n"
        "    dr.while_loop((mi.UInt32(0, 1),), lambda i: i < 3, body)\n\n\ncommand()\n")
    proc = subprocess.run([sys.executable, "-m", "interrupted_loop"], capture_output=True, text=True,
                          cwd=tmp_path, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 130 and proc.stderr.strip() == "mitsuba-active: interrupted", proc.stderr


# An object whose making an interrupt cuts short (as imageio's PNG writer, mid-way
# through its constructor): its finaliser then fails on the attribute never set.
_HALF_MADE = ("import os, signal, time\n\n\nclass HalfMade:\n    def __init__(self):\n"
              "        os.kill(os.getpid(), signal.{signal})\n        time.sleep(5)\n        self.ready = True\n\n"
              "    def __del__(self):\n        self.ready\n\n\n")


def test_an_interrupt_inside_a_constructor_is_one_line_and_exits_130(tmp_path):
    """The finaliser of an object the interrupt cut short in its making prints no traceback."""
    (tmp_path / "interrupted_making.py").write_text(
        _HALF_MADE.format(signal="SIGINT") + "from mitsuba_active.cli.common import one_line_errors\n\n\n"
        "@one_line_errors(libraries=False)\ndef command():\n    HalfMade()\n\n\ncommand()\n")
    proc = subprocess.run([sys.executable, "-m", "interrupted_making"], capture_output=True, text=True,
                          cwd=tmp_path, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 130 and proc.stderr.strip() == "mitsuba-active: interrupted", proc.stderr


def test_an_interrupted_command_leaves_the_process_reporting_as_before():
    """Called in-process, an interrupted command puts Python's unraisable hook back."""
    from mitsuba_active.cli.common import one_line_errors

    @one_line_errors(libraries=False)
    def command():
        raise KeyboardInterrupt

    before = sys.unraisablehook
    with pytest.raises(SystemExit) as exit_:
        command()
    assert exit_.value.code == 130 and sys.unraisablehook is before


def test_a_worker_stopped_inside_a_constructor_prints_nothing(tmp_path):
    """A suite's worker, stopped (SIGTERM) while a job makes an object, exits
    without a traceback from that object's finaliser."""
    (tmp_path / "stopped_worker.py").write_text(
        _HALF_MADE.format(signal="SIGTERM") + "from mitsuba_active import executors\n\n"
        "executors._init_worker(os.getppid())\nexecutors._worker_busy = True\nHalfMade()\n")
    proc = subprocess.run([sys.executable, "-m", "stopped_worker"], capture_output=True, text=True,
                          cwd=tmp_path, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 1 and proc.stderr == "", proc.stderr


@pytest.mark.parametrize("args,needle", [
    (["--planner", "even", "--ensemble", "3"], "trains no ensemble"),
    (["--planner", "fisher", "--ensemble", "3"], "trains 1 field"),
    (["--planner", "variational", "--ensemble", "2"], "trains 1 field"),
    (["--score", "sum", "--planner-option", "form=log"], "give rfe's score once"),
    (["--planner-option", "form=sum", "--planner-option", "form=log"], "form is given twice"),
    (["--planner", "even", "--score", "sum"], "applies to the rfe planner only"),
])
def test_plan_options_that_do_not_apply_are_refused(spot_xml, tmp_path, args, needle):
    out = tmp_path / "o"
    code, text = run_cli("plan", spot_xml, "--out", out, *args)
    assert_one_line_error(code, text, needle)
    assert not out.exists()


def test_the_interior_rig_inside_an_object_says_what_to_use(spot_xml, tmp_path):
    out = tmp_path / "o"
    code, text = run_cli("render", spot_xml, "-o", out, "--rig", "interior", "--candidates", "10")
    assert_one_line_error(code, text, "of the 10 candidate cameras")
    assert "is an object, not a room: use --rig sphere" in text
    assert not out.exists()


def test_a_room_without_room_for_clear_cameras_says_so(shared_data, tmp_path, monkeypatch):
    """In a room, places nearer a surface than the clearance are no places for a camera."""
    monkeypatch.setattr("mitsuba_active.rigs.INTERIOR_CLEARANCE", 0.3)  # no place in the box is that clear
    out = tmp_path / "o"
    code, text = run_cli("render", shared_data / "mitsuba/cbox/cbox.xml", "-o", out, "--rig", "interior",
                         "--candidates", "10")
    assert_one_line_error(code, text, "of the 10 candidate cameras")
    room = load_scene(shared_data / "mitsuba/cbox/cbox.xml")
    clearance = 0.3 * np.linalg.norm(room.bbox_max - room.bbox_min)
    assert f"or closer than {clearance:.3g} to a surface; ask for fewer views" in text
    assert not out.exists()


@pytest.mark.parametrize("command", ["plan", "render"])
def test_candidates_do_not_apply_to_the_xml_rig(spot_xml, tmp_path, command):
    """The XML's own sensors are the candidates: --candidates would be recorded but never used."""
    out = tmp_path / "o"
    code, text = run_cli(command, spot_xml, "--rig", "xml", "--candidates", "50",
                         *(["--out", out] if command == "plan" else ["-o", out]))
    assert_one_line_error(code, text, "--candidates does not apply to --rig xml")
    assert not out.exists()


def test_a_dataset_refuses_spp_and_notes_missing_frames(shared_data, tmp_path):
    mic = shared_data / "datasets" / "nerf_synthetic_mic"
    code, text = run_cli("plan", mic, "--spp", "4", "--out", tmp_path / "a")
    assert_one_line_error(code, text, "--spp applies to scenes")
    code, text = run_cli("plan", mic, "--distance-weight", "0.5", "--out", tmp_path / "a")
    assert_one_line_error(code, text, "(--distance-weight) needs distances, and nerf_synthetic_mic has no depth maps")
    assert not (tmp_path / "a").exists()
    code, text = run_cli("plan", mic, "--heldout", "500", "--planner", "even", "--budget", "2", "--eval-views", "2",
                         "--eval-steps", "5", "--resolution", "25", "--quiet", "--out", tmp_path / "b")
    assert code == 0, text
    assert "note: nerf_synthetic_mic has 25 held-out frames; --heldout 500 uses all of them" in text


def test_scene_writes_only_an_xml_file(tmp_path, shared_data):
    """A scene written as .ply would be XML in a mesh's name (and -o '' a folder's)."""
    for target in (tmp_path / "x" / "spot.ply", ""):
        code, text = run_cli("scene", shared_data / "meshes" / "spot.obj", "-o", target)
        assert_one_line_error(code, text, "the scene file to write must end in .xml")
    assert not (tmp_path / "x").exists()


def test_bench_refuses_lists_that_name_nothing(tmp_path):
    """An empty --planners, --scenes or --seeds would otherwise mean all of them."""
    suite = tmp_path / "s.toml"
    suite.write_text("[[scenes]]\nxml = 'none.xml'\n")
    for option in ("--planners", "--scenes", "--seeds"):
        for value in ("", " , "):
            code, text = run_cli("bench", suite, option, value, "--out", tmp_path / "b")
            assert_one_line_error(code, text, f"{option} names none")
    assert not (tmp_path / "b").exists()


def test_bench_workers_beyond_the_machine_are_refused(tmp_path):
    from tests.conftest import REPO

    cores = os.cpu_count() or 1
    for workers in (0, 4 * cores + 1):
        code, text = run_cli("bench", REPO / "benchmarks" / "suites" / "shared.toml", "--workers", workers,
                             "--out", tmp_path / "b")
        assert_one_line_error(code, text, f"--workers must be between 1 and {4 * cores}")
    assert not (tmp_path / "b").exists()


TINY_PLAN = ["--resolution", "8", "--spp", "1", "--candidates", "4", "--heldout", "1", "--budget", "2",
             "--initial-views", "2", "--eval-views", "2", "--eval-steps", "2", "--planner", "even", "--quiet"]


@pytest.fixture(scope="module")
def finished_run(spot_xml, tmp_path_factory):
    out = tmp_path_factory.mktemp("finished") / "run"
    code, text = run_cli("plan", spot_xml, "--out", out, *TINY_PLAN)
    assert code == 0, text
    return out


@pytest.mark.parametrize("edit, needle", [
    (dict(metrics=5), "its metrics is int, not list"),
    (dict(metrics=[{"views": 2, "psnr": "high"}]), "an entry of its metrics is not the scores at a view count"),
    (dict(metrics=[{"views": 2, "psnr": 20.0}] * 2), "its metrics are at view counts [2, 2], not once each at counts "
                                                  "of its 2 captured views"),
    (dict(metrics=[{"views": 3, "psnr": 20.0}]), "its metrics are at view counts [3], not once each at counts of "
                                                 "its 2 captured views"),
    (dict(versions={"mitsuba": [3]}), "its versions are not names of versions"),
    (dict(wall_seconds="long"), "its wall_seconds is 'long', not a number of seconds"),
    (dict(bbox=[[0, 0], [1, 1]]), "its bbox is [[0, 0], [1, 1]], not two corners of three numbers"),
    (dict(finished="yes"), "its finished is str, not bool"),
])
def test_a_hand_edited_run_record_is_refused_by_every_command(finished_run, spot_xml, tmp_path, edit, needle):
    import json
    import shutil

    from mitsuba_active.bench import Job, _recorded

    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    rec = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**rec, **edit}))
    code, text = run_cli("plan", spot_xml, "--out", out, *TINY_PLAN)
    assert_one_line_error(code, text, f"run.json is damaged ({needle}); remove it to start over")
    code, text = run_cli("export", out)
    assert_one_line_error(code, text, f"run.json is damaged ({needle})")
    assert not (out / "export").exists()
    # A suite neither skips nor reports it: its run refuses the folder.
    assert _recorded(Job("s", "even", 0, str(spot_xml), rec["config"], str(out))) is None


def test_a_run_record_of_another_format_is_named_so(finished_run, spot_xml, tmp_path):
    import json
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    rec = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**rec, "format": 2}))
    for args in (["plan", spot_xml, "--out", out, *TINY_PLAN], ["export", out]):
        code, text = run_cli(*args)
        assert_one_line_error(code, text, "run.json is a run record of format 2, which this version of "
                                          "mitsuba-active does not read (it reads format 1)")


def test_a_run_record_with_a_broken_random_state_or_pose(finished_run, spot_xml, tmp_path):
    import json
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    rec = json.loads((out / "run.json").read_text())
    (out / "run.json").write_text(json.dumps({**rec, "rng_state": {"bit_generator": "PCG64"}}))
    code, text = run_cli("plan", spot_xml, "--out", out, *TINY_PLAN)
    assert_one_line_error(code, text, "its rng_state is not the state of the planner's random stream")
    for pose, needle in (([[1.0]], "to_world must be a 4x4 matrix of numbers"),
                         ([[float("nan")] * 4] * 4, "to_world must be finite")):
        cams = [{**rec["candidates"][0], "to_world": pose}] + rec["candidates"][1:]
        (out / "run.json").write_text(json.dumps({**rec, "candidates": cams}))
        code, text = run_cli("export", out)
        assert_one_line_error(code, text, f"run.json is damaged (one of its candidates: a camera's {needle}")


def test_a_run_record_nested_too_deeply_is_damaged(finished_run, spot_xml, tmp_path):
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    (out / "run.json").write_text("[" * 100_000 + "]" * 100_000)
    code, text = run_cli("plan", spot_xml, "--out", out, *TINY_PLAN)
    assert_one_line_error(code, text, "run.json is damaged (maximum recursion depth exceeded")
    code, text = run_cli("export", out)
    assert_one_line_error(code, text, "run.json is damaged (maximum recursion depth exceeded")


def test_export_refuses_a_folder_that_holds_another_dataset(finished_run, tmp_path):
    """Its transforms.json would be replaced (or a transforms_train.json shadowed); an
    earlier export's is replaced."""
    import json

    for name in ("transforms.json", "transforms_train.json"):
        dataset = tmp_path / name
        (dataset / "images").mkdir(parents=True)
        original = json.dumps({"frames": [{"file_path": "images/r_0.png", "transform_matrix": np.eye(4).tolist()}]})
        (dataset / name).write_text(original)
        code, text = run_cli("export", finished_run, "-o", dataset)
        assert_one_line_error(code, text, f"-o/--output {dataset}: holds a dataset that is not an earlier export "
                                          f"({name}); export into another folder")
        assert (dataset / name).read_text() == original and sorted(p.name for p in dataset.iterdir()) == [
            "images", name]
    for _ in range(2):  # again over the first
        code, text = run_cli("export", finished_run, "-o", tmp_path / "ours")
        assert code == 0, text


def test_export_refuses_damaged_view_files(finished_run, tmp_path):
    import shutil

    for name, damage in (("view_001.png", lambda p: p.write_bytes(p.read_bytes()[:60])),
                         ("view_000.exr", lambda p: p.write_bytes(b"")),
                         ("view_000.png", lambda p: shutil.copy(tmp_path / "run" / "views" / "view_000.exr", p))):
        shutil.rmtree(tmp_path / "run", ignore_errors=True)
        shutil.copytree(finished_run, tmp_path / "run")
        damage(tmp_path / "run" / "views" / name)
        code, text = run_cli("export", tmp_path / "run")
        assert_one_line_error(code, text, f"views/{name} is damaged (it does not read as an image")
        assert not (tmp_path / "run" / "export").exists()
    # A missing distance map is named missing (not damaged), in one line.
    (tmp_path / "run" / "views" / "view_000.png").unlink()
    (tmp_path / "run" / "views" / "view_001.exr").unlink()
    code, text = run_cli("export", tmp_path / "run")
    assert_one_line_error(code, text, "views is missing images or distance maps for views [0, 1]")
    assert not (tmp_path / "run" / "export").exists()


def test_a_run_folder_in_use_is_refused_and_left_alone(finished_run, spot_xml, tmp_path):
    import fcntl
    import shutil

    out = tmp_path / "run"
    shutil.copytree(finished_run, out)
    (out / "run.json").unlink()  # nothing to resume: a failed plan would otherwise clear the folder
    before = sorted(p.name for p in out.iterdir())
    fd = os.open(out, os.O_RDONLY)  # as a run in another process holds it
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        code, text = run_cli("plan", spot_xml, "--out", out, *TINY_PLAN)
        assert_one_line_error(code, text, f"--out {out}: in use by another run")
        assert sorted(p.name for p in out.iterdir()) == before
    finally:
        os.close(fd)
    code, text = run_cli("plan", spot_xml, "--out", out, *TINY_PLAN)
    assert code == 0, text


def test_an_error_naming_text_with_a_line_break_stays_one_line(tmp_path):
    code, text = run_cli("plan", tmp_path / "two\nlines.xml", "--out", tmp_path / "o")
    assert_one_line_error(code, text, "two\\nlines.xml")


def test_image_sizes_must_be_whole_numbers_of_pixels(spot_xml):
    from mitsuba_active.env import SceneSource

    with pytest.raises(UserError, match="whole numbers of pixels, got 16.5x16.5"):
        SceneSource.from_xml(spot_xml, n_candidates=4, n_heldout=1, resolution=16.5)


def _signal_on_import(module: str, signum: str) -> str:
    """Python source that sends its own process ``signal.<signum>`` when ``module`` is first imported."""
    return ("import os, signal, sys\n\n\n"
            "class SignalOnImport:\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            f"        if name == {module!r}:\n"
            "            sys.meta_path.remove(self)\n"
            f"            os.kill(os.getpid(), signal.{signum})\n"
            "        return None\n\n\n"
            "sys.meta_path.insert(0, SignalOnImport())\n")


@pytest.mark.parametrize("module,importer", [("mitsuba", "mitsuba_active"), ("click", "mitsuba_active.cli")])
def test_ctrl_c_while_libraries_load_is_one_line(tmp_path, module, importer):
    """Ctrl-C while Dr.Jit and Mitsuba (or the command line's libraries) load
    is held back until they have loaded: then one line, and the process ends by
    SIGINT, not by an unrelated error inside a half-loaded extension."""
    import signal

    script = _signal_on_import(module, "SIGINT") + f"import {importer}\nprint('imported')\n"
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == -signal.SIGINT and proc.stderr == "mitsuba-active: interrupted\n", proc.stderr
    assert proc.stdout == ""


def test_ctrl_c_while_a_commands_module_loads_is_one_line_and_exit_130(tmp_path):
    """The group imports a command's module when the command runs: Ctrl-C there is held back until the
    import ends, then stops the command as it does inside one."""
    script = (_signal_on_import("mitsuba_active.bench", "SIGINT")
              + "from mitsuba_active.cli import main\nmain(['bench', '--help'], prog_name='mitsuba-active')\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 130 and proc.stderr == "mitsuba-active: interrupted\n", proc.stderr
    assert proc.stdout == ""


def test_a_command_runs_with_stderr_closed(tmp_path, spot_xml):
    """Started with ``2>&-`` (no stderr at all), its progress bars have nowhere to go: it still runs."""
    import shlex

    out = tmp_path / "r"
    command = [sys.executable, "-m", "mitsuba_active", "render", str(spot_xml), "-o", str(out), "--resolution", "8",
               "--candidates", "2", "--heldout", "1", "--spp", "1"]
    proc = subprocess.run(["bash", "-c", shlex.join(command) + " 2>&-"], capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 0 and proc.stdout == f"wrote 2 views to {out}\n", proc
    assert (out / "cand_001.png").is_file()


def test_sigterm_while_the_commands_libraries_load_stops_the_command(tmp_path, shared_data):
    """A SIGTERM that lands while a command loads its libraries (trimesh's imports
    swallow an interrupt raised inside them) stops it as Ctrl-C does: one line,
    exit 130, nothing written."""
    out = tmp_path / "s" / "spot.xml"
    # trimesh imports trimesh.path inside an 'except BaseException'.
    script = ("from mitsuba_active.cli import main\n" + _signal_on_import("trimesh.path", "SIGTERM")
              + f"main(['scene', {str(shared_data / 'meshes' / 'spot.obj')!r}, '-o', {str(out)!r}], "
              "prog_name='mitsuba-active')\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path,
                          env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)))
    assert proc.returncode == 130 and proc.stderr == "mitsuba-active: interrupted\n", proc.stderr
    assert proc.stdout == "" and not out.parent.exists()


def test_plan_notes_eval_views_it_leaves_out_and_an_interior_rig_around_an_object(spot_xml, tmp_path):
    code, text = run_cli("plan", spot_xml, "--planner", "even", "--budget", "2", "--eval-views", "1,2,9",
                         "--eval-steps", "5", "--resolution", "16", "--candidates", "3", "--heldout", "1",
                         "--spp", "2", "--rig", "interior", "--quiet", "--out", tmp_path / "o")
    assert code == 0, text
    assert "note: --eval-views 1, 9 left out: below the 2 initial views or above the budget of 2" in text
    assert "note: spot.xml is an object seen from outside; --rig interior puts the cameras inside" in text


def test_mitsuba_warnings_are_plain_lines_on_stderr(tmp_path):
    """A scene Mitsuba loads with a complaint: the command says so once on stderr, without colour codes,
    and its output on stdout stays its own. In-process, Mitsuba's own logging is put back afterwards."""
    import mitsuba as mi

    xml = tmp_path / "s.xml"
    spheres = "".join(f'<shape type="sphere"><transform name="to_world"><scale x="0.3" y="{0.4 + i / 10}" z="0.3"/>'
                      '</transform><bsdf type="diffuse"/></shape>' for i in range(3))
    xml.write_text(f'<scene version="3.0.0"><emitter type="constant"/>{spheres}</scene>')
    command = ["render", str(xml), "-o", str(tmp_path / "r"), "--candidates", "2", "--heldout", "1",
               "--resolution", "8", "--spp", "1", "--views", "1"]
    proc = subprocess.run([sys.executable, "-m", "mitsuba_active", *command], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "\x1b" not in proc.stdout + proc.stderr and "WARN" not in proc.stdout, proc.stdout
    warned = [ln for ln in proc.stderr.splitlines() if "non-uniform scaling" in ln]
    assert warned == ["mitsuba-active: warning: [Sphere] 'to_world' transform shouldn't contain non-uniform "
                      "scaling!"], proc.stderr
    logger = mi.logger()

    def state():
        f = logger.formatter()
        return ([logger.appender(i) for i in range(logger.appender_count())], f.has_date(), f.has_thread(),
                f.has_log_level())

    before = state()
    # Warnings made errors (python -W error) do not fail the scene's loading from inside Mitsuba.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, text = run_cli(*command)
    assert code == 0 and "mitsuba-active: warning: [Sphere] 'to_world' transform" in text, text
    assert state() == before


def test_a_warning_stays_one_line(tmp_path):
    """A dataset frame whose missing image has a line break in its name: the warning escapes it."""
    from tests.test_datasets import write_dataset

    write_dataset(tmp_path / "ds", n=10, frame_extra={1: {"file_path": "images/gone\nmissing.png"}})
    command = ["plan", str(tmp_path / "ds"), "--planner", "even", "--budget", "2", "--initial-views", "1",
               "--eval-views", "2", "--eval-steps", "5", "--candidates", "4", "--heldout", "1", "--quiet",
               "--out", str(tmp_path / "run")]
    proc = subprocess.run([sys.executable, "-m", "mitsuba_active", *command], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    warned = [ln for ln in proc.stderr.splitlines() if "warning:" in ln]
    assert len(warned) == 1 and warned[0].endswith("skipped 1 of 10 frames whose image file is missing "
                                                   f"(e.g. {tmp_path / 'ds' / 'images'}/gone\\nmissing.png)"), \
        proc.stderr


@pytest.mark.parametrize("command, message", [
    (["scene", "{folder}", "-o", "{out}/x.xml"], "mesh file {folder} is a folder, not a file"),
    (["scene", "{spot}", "-o", "{out}/x.xml", "--texture", "{folder}"], "texture {folder} is not a file"),
    (["scene", "{spot}", "-o", "{folder}"], "the scene file to write must end in .xml"),
    (["render", "{folder}", "-o", "{out}"], "{folder} is a folder, not a scene XML file"),
])
def test_a_folder_where_a_file_is_named_is_one_line(tmp_path, shared_data, command, message):
    names = dict(folder=tmp_path / "folder", out=tmp_path / "out", spot=shared_data / "meshes" / "spot.obj")
    names["folder"].mkdir()
    code, output = run_cli(*[part.format(**names) for part in command])
    assert_one_line_error(code, output, message.format(**names))
    assert not (tmp_path / "out").exists()


def test_a_write_that_fails_names_the_output(tmp_path):
    """A full disk fails a write, which names no file: the message names the output being written."""
    import errno

    from mitsuba_active.imageio_utils import atomic_write

    with pytest.raises(OSError) as err:
        with atomic_write(tmp_path / "view.png") as tmp:
            tmp.write_bytes(b"half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert err.value.filename == str(tmp_path / "view.png") and list(tmp_path.iterdir()) == []


# -- the command line's own text ---------------------------------------------------------

def test_every_option_of_every_command_has_help():
    import click

    ctx = click.Context(main)
    missing = [f"{name} {'/'.join(p.opts)}" for name, command in [("mitsuba-active", main), *main.commands.items()]
               for p in command.get_params(ctx) if isinstance(p, click.Option) and not p.hidden and not p.help]
    assert not missing, missing


def test_command_summaries_read_whole_at_any_width():
    for width in (80, 40):
        result = CliRunner().invoke(main, ["--help"], terminal_width=width)
        listing = result.output.partition("Commands:")[2]
        assert result.exit_code == 0 and listing and "..." not in listing, result.output
        text = " ".join(listing.split())
        for command in main.commands.values():
            first = " ".join(command.help.split("\n\n")[0].split())
            assert first in text, (first, result.output)


# -- names of planners and other choices ----------------------------------------------------

def test_a_planner_is_named_in_any_case(spot_xml, tmp_path, monkeypatch):
    import json

    monkeypatch.chdir(tmp_path)
    code, text = run_cli("plan", spot_xml, *[a for a in TINY_PLAN if a not in ("--planner", "even")],
                         "--planner", "RFE", "--score", "log", "--rig", "Sphere", "--field", "FAST")
    assert code == 0, text
    config = json.loads((tmp_path / "runs" / "spot-rfe-seed0" / "run.json").read_text())["config"]
    assert (config["planner"], config["rig"], config["field_preset"]) == ("rfe", "sphere", "fast")


def test_a_mistyped_planner_is_answered_with_the_nearest_name(spot_xml, out):
    code, text = run_cli("plan", spot_xml, "--out", out, "--planner", "rfr")
    assert_one_line_error(code, text, "unknown planner 'rfr' (did you mean 'rfe'?); choose one of coverage, even")
    assert not out.exists()


def test_a_mistyped_choice_is_answered_with_the_nearest(spot_xml, out):
    result = CliRunner().invoke(main, ["plan", str(spot_xml), "--out", str(out), "--rig", "spere"])
    assert result.exit_code == 2 and "(Did you mean 'sphere'?)" in result.output, result.output


@pytest.mark.parametrize("name, hint", [("pla", " Did you mean 'plan'?"), ("xyz", "")])
def test_a_mistyped_command_is_answered_with_the_nearest(name, hint):
    result = CliRunner().invoke(main, [name])
    assert result.exit_code == 2 and f"Error: No such command '{name}'.{hint}\n" in result.output, result.output


# -- errors about the output folder name its option ------------------------------------------

def test_errors_about_the_out_folder_name_it(finished_run, spot_xml, tmp_path, monkeypatch):
    import shutil

    blocker = tmp_path / "afile"
    blocker.write_text("")
    code, text = run_cli("plan", spot_xml, "--out", blocker / "run", *TINY_PLAN)
    assert_one_line_error(code, text, f"--out {blocker / 'run'}: {blocker} is a file, where a folder is needed")
    code, text = run_cli("plan", spot_xml, "--out", finished_run, *TINY_PLAN, "--seed", "3")
    assert_one_line_error(code, text, f"--out {finished_run}: holds a run with other settings (seed: 0 -> 3); "
                                      "choose another run folder")
    # The default folder too: --out is where to name another.
    monkeypatch.chdir(tmp_path)
    shutil.copytree(finished_run, tmp_path / "runs" / "spot-even-seed3")
    code, text = run_cli("plan", spot_xml, *TINY_PLAN, "--seed", "3")
    assert_one_line_error(code, text, f"--out {Path('runs') / 'spot-even-seed3'}: holds a run with other settings "
                                      "(seed: 0 -> 3)")


def test_a_dataset_without_any_of_its_images_is_one_line(shared_data, tmp_path):
    import shutil

    shutil.copy(shared_data / "datasets" / "nerf_synthetic_mic" / "transforms_train.json",
                tmp_path / "transforms.json")
    proc = subprocess.run([sys.executable, "-m", "mitsuba_active", "plan", str(tmp_path / "transforms.json"),
                           "--out", str(tmp_path / "run"), "--quiet"], capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"mitsuba-active: error: {tmp_path / 'transforms.json'}: none "
                                                   "of the dataset's image files exist"), proc.stderr
    assert not (tmp_path / "run").exists()


# -- precision of what runs write -------------------------------------------------------------

def test_metrics_csv_prints_each_figure_to_its_decimals(finished_run):
    import csv
    import re

    from mitsuba_active.metrics import DECIMALS

    rows = list(csv.DictReader((finished_run / "metrics.csv").open()))
    assert rows
    for row in rows:
        assert re.fullmatch(r"\d+", row.pop("views"))
        for column, value in row.items():
            # SSIM needs 11x11 pixels: empty here.
            assert value == "" or re.fullmatch(rf"-?\d+\.\d{{{DECIMALS[column]}}}", value), (column, value)
    assert {DECIMALS[c] for c in ("psnr", "ssim", "distance_error", "fit_psnr")} == {4}
