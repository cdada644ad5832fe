"""The PSF atlas: kernels recovered from known blurs, on masks of any shape, with intervals that cover what the noise
does, cells marked unmeasured where the data cannot tell, and ``atlas.npz`` in its documented layout."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.signal import fftconvolve

from dp5k_diagnose import atlas as A


def half_disc(h: int, radius: float, side: int = -1, ss: int = 8) -> np.ndarray:
    """(2h+1)^2 area coverage of the half disc x < 0 (``side`` -1) or x > 0 (+1) of ``radius`` px, summing to 1/2."""
    u = (np.arange((2 * h + 1) * ss) + 0.5) / ss - (h + 0.5)
    X, Y = np.meshgrid(u, u)
    w = ((X**2 + Y**2) <= radius**2) & (side * X > 0)
    k = w.reshape(2 * h + 1, ss, 2 * h + 1, ss).sum((1, 3)).astype(np.float64)
    return k / k.sum() / 2


def texture(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    """(3, H, W) smooth value noise plus fine detail, like the test renderers' textures."""
    def noise(cell: float) -> np.ndarray:
        g = rng.uniform(0, 1, (int(H / cell) + 2, int(W / cell) + 2))
        return cv2.resize(g, (W, H), interpolation=cv2.INTER_CUBIC)
    return np.stack([0.6 * noise(5.0) + 0.4 * noise(1.5) for _ in range(3)])


def blurred_pairs(coc_px: float, radius: float, mask: str, n: int = 5, noise: float = 1e-3, seed: int = 0,
                  H: int = 120, W: int = 160) -> tuple[list[A.PairImages], list[A.Views], np.ndarray, np.ndarray]:
    """Pairs whose views are the sharp image blurred by a left/right half disc (constant ``coc_px``), scored on the
    interior (``full``) or on diagonal bands 10 px wide (``band``: a slanted plane's CoC bin)."""
    rng = np.random.default_rng(seed)
    h = A.Grid.of((int(A.FINE.of(np.array([coc_px]))[0]), -1)).h
    kl, kr = half_disc(h, radius, -1), half_disc(h, radius, +1)
    yy, xx = np.mgrid[0:H, 0:W]
    field = np.stack([(xx - (W - 1) / 2) / ((W - 1) / 2), (yy - (H - 1) / 2) / ((H - 1) / 2)])
    imgs, views = [], []
    for i in range(n):
        s = texture(rng, H, W)
        L = np.stack([fftconvolve(s[c], kl, mode="same") for c in range(3)]) + rng.normal(0, noise, (3, H, W))
        R = np.stack([fftconvolve(s[c], kr, mode="same") for c in range(3)]) + rng.normal(0, noise, (3, H, W))
        score = np.zeros((H, W), bool)
        score[30:-30, 30:-30] = True
        if mask == "band":
            score &= ((xx + 0.5 * yy) % 40) < 10
        imgs.append(A.PairImages(f"p{i}", s, np.full((H, W), coc_px), score, field))
        views.append((L, R))
    return imgs, views, kl, kr


def centroid_x(k: np.ndarray) -> float:
    h = k.shape[-1] // 2
    return float((k * np.arange(-h, h + 1)[None, :]).sum() / k.sum())


@pytest.mark.parametrize("mask", ["full", "band"])
def test_kernels_of_a_known_blur_are_recovered_on_any_mask(mask: str) -> None:
    """The least squares use the exact Gram of the sharp patches: on a 10 px band (a slanted plane's CoC bin) the
    half discs come back as well as on a whole region (a Toeplitz approximation of the Gram, exact only for whole
    regions, misplaced half of the kernel's mass on the band)."""
    imgs, views, kl, kr = blurred_pairs(8.0, 4.0, mask)
    atlas = A.measure_atlas(imgs, {"m": views}, n_boot=20)
    key = (int(A.FINE.of(np.array([8.0]))[0]), -1)
    k = atlas.kernels(key, "m").mean(1)  # channels averaged: (2, K, K)
    for got, want in ((k[0], kl), (k[1], kr)):
        assert np.abs(got - want).sum() / np.abs(want).sum() < 0.3
        assert centroid_x(got) == pytest.approx(centroid_x(want), abs=0.05)
    assert centroid_x(k[0]) < 0 < centroid_x(k[1])
    gain = atlas.dc_gain(key, "m").mean(1)
    assert gain == pytest.approx([0.5, 0.5], abs=0.01)


def test_a_wide_kernel_is_solved_on_blocks_and_keeps_its_centroid() -> None:
    imgs, views, kl, _ = blurred_pairs(30.0, 14.0, "full", H=170, W=220)
    key = (int(A.FINE.of(np.array([30.0]))[0]), -1)
    grid = A.Grid.of(key)
    assert grid.bs > 1 and grid.side <= A.MAX_GRID
    atlas = A.measure_atlas(imgs, {"m": views}, n_boot=20)
    k = atlas.kernels(key, "m").mean(1)[0]
    assert k.shape == kl.shape
    assert centroid_x(k) == pytest.approx(centroid_x(kl), abs=0.25)


def test_the_bootstrap_covers_what_resampling_does() -> None:
    """Over independent datasets (new scenes and new noise: what a bootstrap over pairs stands for), a kernel's
    centroid varies by about the bootstrap's standard deviation, neither far more (intervals too narrow: false
    differences) nor far less (no power). Holding the scenes fixed would leave out the scene-to-scene part that the
    pair bootstrap rightly carries."""
    key = (int(A.FINE.of(np.array([8.0]))[0]), -1)
    cx, sd = [], []
    for draw in range(8):
        imgs, views, _, _ = blurred_pairs(8.0, 4.0, "full", n=3, noise=0.02, seed=draw)
        m = A.AtlasMeasurer(imgs, 100, 0)
        m.measure("m", views, (0.0, 0.02))
        cx.append(centroid_x(m.atlas.kernels(key, "m")[0, 1]))
        sd.append(np.std([centroid_x(k) for k in m.atlas.kernels(key, "m", boot=True)[:, 0, 1]]))
    spread, claimed = float(np.std(cx, ddof=1)), float(np.mean(sd))
    assert claimed / 2 < spread < 1.5 * claimed, (spread, claimed)


def test_cells_without_enough_data_are_unmeasured_and_say_why() -> None:
    imgs, views, _, _ = blurred_pairs(8.0, 4.0, "full", n=1)
    atlas = A.measure_atlas(imgs, {"m": views}, n_boot=10)
    key = (int(A.FINE.of(np.array([8.0]))[0]), -1)
    assert not atlas.cells[key].measured and "1 pair(s)" in atlas.cells[key].unmeasured
    imgs, views, _, _ = blurred_pairs(8.0, 4.0, "full", n=3)
    for img in imgs:
        img.score[:] = False
        img.score[60:64, 80:84] = True  # 16 px per pair for a 19 x 19 kernel
    atlas = A.measure_atlas(imgs, {"m": views}, n_boot=10)
    assert "unknowns" in atlas.cells[key].unmeasured and key in atlas.unmeasured()


def test_atlas_npz_has_the_documented_layout(tmp_path: Path) -> None:
    imgs, views, kl, _ = blurred_pairs(8.0, 4.0, "full", n=3)
    atlas = A.measure_atlas(imgs, {"measured": views, "simulator": views}, n_boot=10)
    A.save_atlas(tmp_path / "atlas.npz", atlas)
    z = np.load(tmp_path / "atlas.npz")
    assert str(z["format"]) == "dp5k-atlas" and int(z["version"]) == 1
    assert list(z["view_sets"]) == ["measured", "simulator"] and list(z["pair_ids"]) == ["p0", "p1", "p2"]
    cells = z["cells"]
    row = int(np.flatnonzero((cells[:, 0] == int(A.FINE.of(np.array([8.0]))[0])) & (cells[:, 1] == -1))[0])
    b, zone, h, bs, measured = cells[row]
    assert measured == 1 and z[f"kernel_{row}"].shape == (2, 2, 3, 2 * h + 1, 2 * h + 1)
    assert z["cell_coc_px"][row, 2] == pytest.approx(8.0)
    assert np.abs(z[f"kernel_{row}"][0, 0].mean(0) - kl).sum() / np.abs(kl).sum() < 0.3
    assert z["dc_gain"].shape == (len(cells), 2, 2, 3)
