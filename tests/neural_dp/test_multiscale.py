"""Multi-scale kernels of the Neural DP Simulator (``ModelConfig.multiscale_levels``): reach, mirror, exact extension."""

from __future__ import annotations

from dataclasses import asdict

import pytest
import torch

from dp5k_common.errors import BadInputError
from neural_dp.kernels import _apply_kernels_unfold, apply_kernels
from neural_dp.model import ModelConfig, UNetKPN, box_prefilter, extend_multiscale
from neural_dp.simulators.neural import NeuralDPSimulator


@pytest.mark.parametrize("dilation", [2, 4])
@pytest.mark.parametrize("per_channel", [False, True])
def test_dilated_shift_and_accumulate_equals_unfold_reference(dilation: int, per_channel: bool) -> None:
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 19, 23, generator=g)
    w = torch.rand(2, 3, 25, 19, 23, generator=g) if per_channel else torch.rand(2, 25, 19, 23, generator=g)
    torch.testing.assert_close(apply_kernels(x, w, dilation=dilation), _apply_kernels_unfold(x, w, dilation=dilation))


def test_dilated_tap_reads_dilation_times_offset() -> None:
    x = torch.arange(40.0).view(1, 1, 1, 40).expand(1, 1, 3, 40).contiguous()
    w = torch.zeros(1, 25, 3, 40)
    w[:, 2 * 5 + 0] = 1.0  # tap (row 2, col 0): offset -2 columns, times the dilation
    assert apply_kernels(x, w, dilation=4)[0, 0, 1, 20].item() == 12.0


@pytest.mark.parametrize("d", [2, 3, 4, 8])
def test_box_prefilter_keeps_flat_images_and_its_shifts_tile_the_line(d: int) -> None:
    flat = torch.full((1, 2, 12, 20), 0.3)
    torch.testing.assert_close(box_prefilter(flat, d), flat)
    line = torch.zeros(1, 1, 9, 41)
    line[..., 20] = 1.0  # a vertical line: the row through it is the 1-D filter centred on column 20
    taps = box_prefilter(line, d)[0, 0, 4]
    assert abs(float((taps * torch.arange(41.0)).sum()) - 20.0) < 1e-5  # centred
    # copies of the filter shifted by multiples of d sum to a constant: dilated taps leave no gaps or overlaps
    for off in range(d):
        assert abs(float(taps[off::d].sum()) - 1.0 / d) < 1e-6


def test_default_is_the_single_scale_model_and_old_checkpoints_load(tmp_path) -> None:
    cfg = ModelConfig(base_channels=4, levels=2)
    assert cfg.multiscale_levels == 0
    net = UNetKPN(cfg)
    assert net.scale_head is None and net.reach_px == 2
    assert not any(k.startswith("scale_head") for k in net.state_dict())
    old_cfg = {k: v for k, v in asdict(cfg).items() if k != "multiscale_levels"}  # a checkpoint from before
    torch.save({"model": net.state_dict(), "model_config": old_cfg}, tmp_path / "old.pt")
    sim = NeuralDPSimulator.from_checkpoint(tmp_path / "old.pt")
    assert sim.cfg.multiscale_levels == 0


@pytest.mark.parametrize("per_channel", [False, True])
def test_extension_reproduces_the_trained_network_exactly(per_channel: bool) -> None:
    torch.manual_seed(0)
    net = UNetKPN(ModelConfig(base_channels=4, levels=2, norm="group", kernel_per_channel=per_channel))
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.2 * torch.randn_like(p))  # a "trained" network, far from the identity init
    net.eval()
    ext = extend_multiscale(net, 3)
    assert ext.dilations == (2, 4, 8) and ext.reach_px == 2 * 8 + 4
    sharp, inputs = torch.rand(2, 3, 27, 35), torch.rand(2, 5, 27, 35)
    with torch.no_grad():
        a, b = net(sharp, inputs), ext(sharp, inputs)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    # and fine-tuning can move it: the blend head gets a gradient at init
    ext.train()
    left, right = ext(sharp, inputs)
    (left.square().mean() + right.mean()).backward()
    assert ext.scale_head is not None and ext.scale_head.weight.grad is not None
    assert float(ext.scale_head.weight.grad[-3:].abs().sum()) > 0
    with pytest.raises(BadInputError):
        extend_multiscale(ext, 1)


def test_multiscale_kernel_moves_content_beyond_5x5_reach_and_right_view_mirrors() -> None:
    """A 5 x 5 kernel moves content at most 2 px; the dilation-4 scale moves it 8 px, mirrored in the right view."""
    net = UNetKPN(ModelConfig(base_channels=4, levels=2, multiscale_levels=2))
    assert net.scale_head is not None
    nk = net.n_kernel
    with torch.no_grad():
        net.view_gain.fill_(1.0)
        sb = torch.zeros_like(net.scale_head.bias)
        sb[1 * nk + 2 * 5 + 0] = 60.0  # scale 2 (d = 4): delta at (row 2, col 0), gathers x - 8: moves right
        sb[2 * nk + 1] = 20.0  # blend weight of d = 4: tanh(20) = 1
        net.scale_head.bias.copy_(sb)
    net.eval()
    sharp = torch.zeros(1, 3, 32, 48)
    sharp[..., 16, 20] = 1.0
    with torch.no_grad():
        left, right = net(sharp, torch.zeros(1, 5, 32, 48))
    cols = torch.arange(48.0)
    cx_l = float((left[0, 0].sum(0) * cols).sum() / left[0, 0].sum())
    cx_r = float((right[0, 0].sum(0) * cols).sum() / right[0, 0].sum())
    assert abs(cx_l - 28.0) < 1e-3 and abs(cx_r - 12.0) < 1e-3
    torch.testing.assert_close(left.sum(), sharp.sum())  # the affine blend keeps the energy


def test_a_run_saved_before_the_option_existed_still_resumes(tmp_path) -> None:
    from neural_dp.config import load_config
    from neural_dp.train import train
    from dp5k_testing.tiny_dataset import make_tiny_dataset

    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3, W=48, H=32)
    tiny = ["model.base_channels=4", "model.levels=2", "data.crop_px=32", "data.batch_size=2",
            "data.samples_per_epoch=2", "device=cpu"]
    train(ds, tmp_path / "run", load_config(None, tiny + ["optim.epochs=1"]))
    state = torch.load(tmp_path / "run" / "last.pt", weights_only=True)
    del state["model_config"]["multiscale_levels"]  # as written before multiscale_levels existed
    torch.save(state, tmp_path / "run" / "last.pt")
    assert train(ds, tmp_path / "run", load_config(None, tiny + ["optim.epochs=2"])).epochs_done == 2
    with pytest.raises(BadInputError):  # a real config change is still refused
        train(ds, tmp_path / "run", load_config(None, tiny + ["optim.epochs=3", "model.multiscale_levels=1"]))
