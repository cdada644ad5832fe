"""Quality on studio data with realistic effects, suite-sized.

After a short CPU training (32 steps of a small network) the Neural DP Simulator beats every peer on
masked PSNR of the held-out test split. SSIM needs a longer training to pass the peers (the residual
images still carry artefacts in flat regions after 32 steps), so the PSNR *and* SSIM claim is checked by
the full run, ``benchmarks/quality_simulators.py``, whose table and settings are in docs/simulators.md.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from dp5k_capture.sim.studio.dataset import make_dataset
from neural_dp.config import load_config
from neural_dp.evaluate import evaluate
from neural_dp.simulators.registry import PEERS
from neural_dp.train import train

EFFECTS = {"lr_gain_imbalance": 1.0, "psf_profile": 1.0, "disparity_scale": 1.0, "field_varying_psf": 1.0}
SHORT = ["device=cpu", "data.crop_px=64", "data.batch_size=4", "data.samples_per_epoch=64", "data.val_pairs=4",
         "model.base_channels=8", "model.levels=3", "optim.epochs=2", "optim.lr=3e-3"]


@pytest.mark.slow
def test_neural_beats_every_peer_on_psnr_of_held_out_studio_pairs(tmp_path: Path) -> None:
    ds = make_dataset(tmp_path / "studio", scenes=5, effects=EFFECTS, size=(128, 96), f_numbers=(1.8, 2.8), seed=3)
    run = train(ds, tmp_path / "run", load_config(None, SHORT))
    assert run.steps == 32
    res = evaluate(ds, tmp_path / "eval", split="test", simulators=[*PEERS, "neural"],
                   checkpoint=tmp_path / "run" / "best.pt", figures=0)
    m = res.means
    for peer in PEERS:
        assert m["neural"]["psnr"] > m[peer]["psnr"] + 1.0, res.table_md
        assert m["neural"]["mae"] < m[peer]["mae"], res.table_md
