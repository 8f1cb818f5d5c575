import imageio.v3 as iio
import numpy as np
import pytest

from mitsuba_active.cameras import fibonacci_sphere, snapped_up
from mitsuba_active.report import plot_views, up_vertical


@pytest.mark.parametrize("up", [(0, 1, 0), (0, 0, 1), (1, 0, 0), (0, -1, 0)])
def test_up_is_drawn_vertically_in_a_right_handed_frame(up):
    basis = up_vertical(np.eye(3), up)  # rows: the images of the world axes
    assert np.allclose(up_vertical([up], up), [[0, 0, 1]])
    assert np.allclose(basis @ basis.T, np.eye(3)) and np.linalg.det(basis) == pytest.approx(1.0)


@pytest.mark.parametrize("up", [(0, 0, 1), (0, -1, 0), (1, 0, 0)])
def test_the_up_axis_of_a_camera_rig(up):
    assert np.array_equal(snapped_up(fibonacci_sphere(20, (0, 0, 0), 2.0, up=up)), up)
    assert np.array_equal(snapped_up([]), (0, 1, 0))


def test_camera_plot_of_a_run_with_repeats(tmp_path):
    cams = fibonacci_sphere(12, (0, 0, 0), 2.0)
    path = plot_views(cams[:10], [3, 3, 7, 0], cams[10:], [-0.5] * 3, [0.5] * 3, tmp_path / "views.png",
                      up=(0, 0, 1), initial=2, title="t")
    image = iio.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0
    # Without held-out views or captures (a run that has not chosen anything yet).
    assert plot_views(cams, [], [], [-0.5] * 3, [0.5] * 3, tmp_path / "empty.png").is_file()


def test_atomic_write_leaves_the_file_whole_or_absent(tmp_path):
    import os

    from mitsuba_active.imageio_utils import atomic_write

    target = tmp_path / "a" / "out.json"
    with pytest.raises(KeyboardInterrupt):
        with atomic_write(target) as tmp:
            tmp.write_text("half")
            raise KeyboardInterrupt
    assert not target.exists() and list((tmp_path / "a").iterdir()) == []
    with atomic_write(target) as tmp:
        tmp.write_text("whole")
    assert target.read_text() == "whole" and list((tmp_path / "a").iterdir()) == [target]
    mask = os.umask(0)
    os.umask(mask)
    assert target.stat().st_mode & 0o777 == 0o666 & ~mask  # the usual permissions, not a temp file's 0600


def test_a_replaced_folder_is_whole_before_and_after(tmp_path):
    from mitsuba_active.imageio_utils import replaced_folder

    target = tmp_path / "report"
    target.mkdir()
    (target / "old.md").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with replaced_folder(target) as folder:
            (folder / "new.md").write_text("half")
            raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["report"] and [p.name for p in target.iterdir()] == ["old.md"]
    with replaced_folder(target) as folder:
        (folder / "new.md").write_text("new")
    assert [p.name for p in tmp_path.iterdir()] == ["report"] and [p.name for p in target.iterdir()] == ["new.md"]
    with replaced_folder(tmp_path / "fresh" / "report") as folder:  # a folder that was not there
        (folder / "a.md").write_text("a")
    assert (tmp_path / "fresh" / "report" / "a.md").read_text() == "a"
