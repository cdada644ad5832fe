"""dp5k synthesize: RGBD folders -> a format-v1 DP dataset (units, sensor adjustment, resume, bad input)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.dataset import DatasetReader
from dp5k_common.errors import BadInputError, PartialFailureError
from dp5k_common.optics import coc_diameter_px, thin_lens_focal_length_mm
from neural_dp.synthesize import SynthConfig, random_focus, synthesize


def _frames(root: Path, n: int = 3, W: int = 64, H: int = 48) -> None:
    rng = np.random.default_rng(0)
    for i in range(n):
        f = root / f"frame_{i:02d}"
        f.mkdir(parents=True)
        img = (rng.uniform(0, 1, (H, W, 3)) * 255).astype(np.uint8)
        cv2.imwrite(str(f / "image.png"), img)
        depth = np.tile(np.linspace(600, 4000 + 500 * i, W), (H, 1))
        depth[:4, :4] = 0
        if i == 1:
            np.save(f / "depth.npy", depth / 1000.0)  # metres, with --depth-scale 1000
        else:
            cv2.imwrite(str(f / "depth.png"), depth.astype(np.uint16))
        (f / "intrinsics.json").write_text(json.dumps({"fx": 60.0, "fy": 60.0, "cx": W / 2, "cy": H / 2,
                                                       "width": W, "height": H}))


def test_synthesize_writes_a_valid_dataset_with_consistent_optics(tmp_path: Path) -> None:
    _frames(tmp_path / "in")
    cfg = SynthConfig(simulator="disk", f_numbers=(1.8,), depth_scale=1000.0, max_coc_px=8.0)
    summary = synthesize(tmp_path / "in", tmp_path / "out", cfg)
    assert summary["written"] == 3 and summary["pairs"] == 3
    reader = DatasetReader(tmp_path / "out")
    for pid in reader.ids():
        pair = reader.load(pid)
        p = pair.params
        # Eq. 7 with the pinhole focal length in mm (fx px times the pitch in mm), never mm-as-px
        assert p.focal_length_mm == pytest.approx(thin_lens_focal_length_mm(60.0 * p.pixel_pitch_mm, p.focus_distance_mm))
        coc = coc_diameter_px(pair.depth_mm, p.focus_distance_mm, p.focal_length_mm, p.f_number, p.pixel_pitch_mm)
        np.testing.assert_allclose(pair.coc_px[pair.valid], coc[pair.valid], rtol=1e-4, atol=1e-3)
        # the 5.3.1 sensor adjustment puts the 99th-percentile |CoC| at f/1.8 on the target
        assert np.percentile(np.abs(pair.coc_px[pair.valid]), 99) == pytest.approx(8.0, rel=0.02)
        # focus distance = mean depth of a 60x40 window around the focus point
        x, y = p.focus_point_px
        assert pair.depth_mm.min() <= p.focus_distance_mm <= pair.depth_mm.max()
        assert 0 <= x < 64 and 0 <= y < 48
        assert not np.allclose(pair.left, pair.right)  # a DP pair, not two copies


def test_resume_skips_finished_frames_and_is_deterministic(tmp_path: Path) -> None:
    _frames(tmp_path / "in")
    cfg = SynthConfig(simulator="disk", depth_scale=1000.0)
    synthesize(tmp_path / "in", tmp_path / "out", cfg)
    before = json.loads((tmp_path / "out" / "pairs" / "frame_02" / "params.json").read_text())
    again = synthesize(tmp_path / "in", tmp_path / "out", cfg)
    assert again["written"] == 0 and again["skipped"] == 3
    import shutil

    shutil.rmtree(tmp_path / "out" / "pairs" / "frame_02")  # as if killed while writing this frame:
    half_written = tmp_path / "out" / "pairs" / ".tmp-frame_02-k1ll3d_x"
    (half_written / "x").mkdir(parents=True)
    not_ours = tmp_path / "out" / "pairs" / ".tmp-frame_02-x-k1ll3d_x"  # a pair 'frame_02-x' being written
    not_ours.mkdir()
    third = synthesize(tmp_path / "in", tmp_path / "out", cfg)
    assert third["written"] == 1
    assert not half_written.exists() and not_ours.exists()
    assert json.loads((tmp_path / "out" / "pairs" / "frame_02" / "params.json").read_text()) == before


def test_bad_frame_is_reported_and_the_rest_is_kept(tmp_path: Path) -> None:
    _frames(tmp_path / "in")
    (tmp_path / "in" / "frame_00" / "intrinsics.json").unlink()
    with pytest.raises(PartialFailureError, match="1 of 3"):
        synthesize(tmp_path / "in", tmp_path / "out", SynthConfig(simulator="disk", depth_scale=1000.0))
    assert len(DatasetReader(tmp_path / "out").ids()) == 2
    res = CliRunner().invoke(main, ["-q", "synthesize", str(tmp_path / "in"), str(tmp_path / "out2"),
                                    "--simulator", "disk", "--depth-scale", "1000"])
    assert res.exit_code == 8 and "intrinsics.json" in res.output


def test_random_focus_window_mean() -> None:
    depth = np.full((768, 1024), 3000.0)
    depth[:, 512:] = 1000.0
    focus, (x, y) = random_focus(depth, np.random.default_rng(1))
    assert 100 <= x <= 924 and 100 <= y <= 668
    x0 = int(np.clip(x - 30, 0, 1024 - 60))
    y0 = int(np.clip(y - 20, 0, 768 - 40))
    assert focus == pytest.approx(depth[y0 : y0 + 40, x0 : x0 + 60].mean())


def test_base_simulator_reads_rgbd_frames_as_all_in_focus(tmp_path: Path) -> None:
    """An RGBD frame is the radiance itself: the physical base model must not undo an f/22 blur it never had
    (written pairs say sharp_f_number 0, and the batches synthesize renders carry it)."""
    import torch

    from dp5k_learn.batch import DPBatch
    from neural_dp.simulators.base import BaseModel

    _frames(tmp_path / "in", n=1)
    synthesize(tmp_path / "in", tmp_path / "out", SynthConfig(simulator="base", f_numbers=(1.8,), depth_scale=1000.0,
                                                               max_coc_px=12.0, noise="none"))  # the optics alone
    reader = DatasetReader(tmp_path / "out")
    pair = reader.load(reader.ids()[0])
    assert pair.params.sharp_f_number == 0.0
    batch = DPBatch.from_pairs([pair])
    written = batch.left[0]
    as_radiance = BaseModel(sharp_deblur_iters=0)(batch)[0][0]
    batch.sharp_f_number = torch.full((1,), 22.0)
    as_f22_frame = BaseModel(sharp_deblur_iters=2)(batch)[0][0]
    assert float((written - as_radiance).abs().max()) < 1e-3
    assert float((written - as_f22_frame).abs().max()) > 1e-2
    # training and evaluation batches (collate_dp) carry the same key
    from dp5k_learn.data import DPPairDataset, collate_dp

    split = next(name for name in reader.splits if reader.ids(name))
    item_batch = collate_dp([DPPairDataset(tmp_path / "out", split)[0]])
    assert item_batch.sharp_f_number is not None and item_batch.sharp_f_number.tolist() == [0.0]


def test_rank_without_torchrun_rendezvous_is_a_one_line_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """RANK / WORLD_SIZE set by hand (no MASTER_ADDR): a clear error before any frame is written."""
    _frames(tmp_path / "in", n=2)
    for key in ("MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    res = CliRunner().invoke(main, ["-q", "synthesize", str(tmp_path / "in"), str(tmp_path / "out"),
                                    "--simulator", "disk", "--depth-scale", "1000"])
    assert res.exit_code == BadInputError.exit_code, res.output
    assert "torchrun" in res.output and "RANK=1" in res.output
    assert not (tmp_path / "out" / "pairs").exists()
