"""The example scripts run end to end at tiny settings."""

import json
import subprocess
import sys

from tests.conftest import REPO


def _run(script, *args):
    proc = subprocess.run([sys.executable, str(REPO / "examples" / script), "--tiny", *args], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def test_custom_scene_example(tmp_path):
    out = _run("custom_scene.py", "--out", str(tmp_path / "c"))
    assert "PSNR" in out
    rec = json.loads((tmp_path / "c" / "run" / "run.json").read_text())
    assert rec["finished"] and len(rec["captured"]) == 4
    assert (tmp_path / "c" / "scene" / "custom.xml").is_file()


def test_compare_planners_example(tmp_path):
    out = _run("compare_planners.py", "--out", str(tmp_path / "p"))
    assert "rfe" in out and "even" in out
    assert (tmp_path / "p" / "psnr.png").is_file()
