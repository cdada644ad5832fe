"""Figures of the demo report (matplotlib, Agg), each saved atomically as a PNG."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

from dp5k_common.dataset import Pair  # noqa: E402
from dp5k_common.io import atomic_path  # noqa: E402
from dp5k_common.rawfile import read_dual_pixel  # noqa: E402
from dp5k_process.rawimage import dp_views  # noqa: E402


def _save(fig: plt.Figure, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)


def display(linear: NDArray[np.floating], exposure: float | None = None) -> NDArray[np.floating]:
    """Linear image -> display (sRGB-like gamma 1/2.2), normalised by its 99.5th percentile unless given."""
    scale = exposure if exposure is not None else float(np.percentile(linear, 99.5)) or 1.0
    return np.clip(linear / scale, 0, 1) ** (1 / 2.2)


def raw_preview(path: Path) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Half-size white-balanced linear previews (H/2, W/2, 3) of a Dual Pixel RAW: the main frame and its
    left photodiode, through processing's own demosaic (``dp5k_process.rawimage.dp_views``)."""
    main, left, _ = dp_views(read_dual_pixel(path))
    return main, left


def capture_sheet(scene_dir: Path, path: Path) -> None:
    """One row per camera: DP main frame at f/1.8, its left photodiode, the f/22 sharp frame, a Gray-code
    structured-light frame and a ChArUco frame, straight from the raw files."""
    cams = sorted(p.name for p in scene_dir.iterdir() if p.is_dir() and p.name.startswith("cam"))
    cols = [("dp_f1.8", "f/1.8 DP raw (L+R)", 0), ("dp_f1.8", "f/1.8 left photodiode", 1), ("sharp_f22", "f/22 sharp", 0),
            ("sl_08", "Gray code (bit 4)", 0), ("charuco_0", "ChArUco view 1", 0)]
    fig, axes = plt.subplots(len(cams), len(cols), figsize=(3.2 * len(cols), 2.4 * len(cams)), squeeze=False)
    for r, cam in enumerate(cams):
        for c, (stem, title, frame) in enumerate(cols):
            ax = axes[r, c]
            ax.axis("off")
            files = sorted((scene_dir / cam).glob(stem + ".*"))
            if not files:
                continue
            main, aux = raw_preview(files[0])
            img = aux * 2 if frame == 1 else main
            ax.imshow(display(img, exposure=float(np.percentile(main, 99.5)) or 1.0))
            ax.set_title(f"{cam}: {title}", fontsize=9)
    fig.suptitle(f"Captured raw session '{scene_dir.name}' (previews from the raw files)", fontsize=11)
    _save(fig, path)


def depth_coc_figure(pair: Pair, path: Path, truth_depth_mm: NDArray[np.floating] | None = None) -> None:
    """Sharp image, depth (mm) and signed CoC (px) with colour bars; with truth, the relative depth error too."""
    panels = 4 if truth_depth_mm is not None else 3
    fig, axes = plt.subplots(1, panels, figsize=(4.3 * panels, 3.3))
    axes[0].imshow(display(pair.sharp))
    axes[0].set_title(f"{pair.pair_id}: sharp (f/22)", fontsize=9)
    depth = np.where(pair.valid, pair.depth_mm, np.nan)
    im = axes[1].imshow(depth / 1000.0, cmap="viridis")
    fig.colorbar(im, ax=axes[1], fraction=0.046, label="depth (m); white = invalid")
    axes[1].set_title("depth", fontsize=9)
    lim = float(np.nanpercentile(np.abs(pair.coc_px), 99)) if np.isfinite(pair.coc_px).any() else 1.0
    im = axes[2].imshow(pair.coc_px, cmap="coolwarm", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=axes[2], fraction=0.046, label="signed CoC diameter (px); + behind focus")
    axes[2].plot([pair.params.focus_point_px[0]], [pair.params.focus_point_px[1]], "k+", ms=12, mew=2)
    axes[2].set_title(f"CoC at f/{pair.params.f_number:g}, F = {pair.params.focus_distance_mm / 1000:.3f} m (+ focus point)", fontsize=9)
    if truth_depth_mm is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.where(pair.valid & (truth_depth_mm > 0), (pair.depth_mm - truth_depth_mm) / truth_depth_mm * 100, np.nan)
        im = axes[3].imshow(rel, cmap="RdBu_r", vmin=-2, vmax=2)
        fig.colorbar(im, ax=axes[3], fraction=0.046, label="relative depth error (%)")
        axes[3].set_title("depth error vs studio ground truth", fontsize=9)
    for ax in axes:
        ax.axis("off")
    _save(fig, path)


def timings_figure(stages: list[tuple[str, float]], path: Path) -> None:
    """Horizontal bar chart of seconds per stage."""
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(stages) + 1))
    names = [s for s, _ in stages][::-1]
    secs = [t for _, t in stages][::-1]
    ax.barh(names, secs, color="#4a7ab0")
    ax.set_xlabel("seconds")
    ax.set_title("time per stage")
    _save(fig, path)


def synthesized_figure(pairs: list[Pair], path: Path) -> None:
    """Per synthesized frame: sharp input, left, right and the right-left difference."""
    fig, axes = plt.subplots(len(pairs), 4, figsize=(13, 2.7 * len(pairs)), squeeze=False)
    for r, pair in enumerate(pairs):
        expo = float(np.percentile(pair.sharp, 99.5)) or 1.0
        axes[r, 0].imshow(display(pair.sharp, expo))
        axes[r, 1].imshow(display(pair.left * 2, expo))
        axes[r, 2].imshow(display(pair.right * 2, expo))
        diff = (pair.right - pair.left).mean(axis=2)
        lim = float(np.percentile(np.abs(diff), 99)) or 1e-3
        im = axes[r, 3].imshow(diff, cmap="coolwarm", vmin=-lim, vmax=lim)
        fig.colorbar(im, ax=axes[r, 3], fraction=0.046)
        for c, t in enumerate(("RGBD input (sharp)", "synthesized left x2", "synthesized right x2", "right - left")):
            axes[r, c].set_title(f"{pair.pair_id}: {t}" if c == 0 else t, fontsize=8)
            axes[r, c].axis("off")
    _save(fig, path)
