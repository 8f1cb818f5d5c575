"""The PyTorch peer of benchmarks/peers/torch_field.py computes what the field computes.

Uncompiled and at tiny sizes (the benchmark itself checks its compiled steps); skipped
where torch, the benchmarks' ``peers`` extra, is not installed.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import mitsuba_active  # noqa: F401  (variant first)
from mitsuba_active.field import Ensemble, FieldConfig
from tests.test_field import BOX, camera_rays, views

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def peer():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "peers" / "torch_field.py"
    spec = importlib.util.spec_from_file_location("torch_field", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_first_step_agrees_with_hashed_levels_and_every_loss_term(peer):
    cfg = FieldConfig(n_levels=3, base_resolution=4, log2_table_size=7, n_samples=16, batch_rays=256,
                      render_batch=1024, init_scale=1.0, empty_weight=0.1, distance_weight=0.5)
    ens = Ensemble(*BOX, n_members=1, config=cfg, seed=2)
    assert ens.layout.dense == (True, False, False)
    rays = views([[0.0, 0.3, 2.2], [2.2, 0.3, 0.0]], width=12, height=12)
    ens.set_rays(*rays)
    trainer = peer.Trainer(peer.peer_of(ens), peer.torch_rays(*rays), compile=False)
    out = peer.check_agreement(ens, trainer, rays)  # raises where they differ
    assert out["loss_ours"] > out["mse_ours"] > 0  # the empty-ray and distance terms count


def test_a_trained_view_dependent_field_renders_alike(peer):
    cfg = FieldConfig(n_levels=2, base_resolution=8, log2_table_size=12, n_samples=16, batch_rays=256,
                      render_batch=1024, view_degree=2, view_resolution=3)
    ens = Ensemble(*BOX, n_members=1, config=cfg, seed=1)
    ens.set_rays(*views([[0.0, 0.3, 2.2], [2.0, 0.5, 0.5]], width=12, height=12))
    ens.train(20)
    assert ens.view_numpy().any()
    o, d = camera_rays([1.0, 1.0, 2.0], width=8, height=8)
    ours = ens.render(o, d)
    field = peer.peer_of(ens)
    with torch.no_grad():
        rgb, distance, opacity = field.render(field.params, torch.tensor(o), torch.tensor(d), clip=True)
    assert np.abs(ours["rgb"][0] - rgb.numpy()).max() < 1e-4
    assert np.abs(ours["opacity"][0] - opacity.numpy()).max() < 1e-4
    assert np.abs(ours["distance"][0] - distance.numpy()).max() < 1e-4
