"""DPDD (Abuolaim & Brown, ECCV 2020, "Defocus Deblurring Using Dual-Pixel Data", MIT): Canon EOS 5D Mark IV
DP views, their combined frame and an all-in-focus f/22 frame per scene; **no depth**.

Layout (``dd_dp_dataset_canon`` as the repository's README and ``DPDNet/data.py``/``config.py`` read it)::

    ROOT/{train,val,test}_c/source/<name>.png   the combined (defocused) frame
    ROOT/{train,val,test}_c/target/<name>.png   the all-in-focus f/22 frame ("sharp")
    ROOT/{train,val,test}_l/source/<name>.png   the left DP view
    ROOT/{train,val,test}_r/source/<name>.png   the right DP view

16-bit PNGs, "processed to an sRGB" (README), 1680 x 1120 in the training/testing release. The splits are kept.

How these pairs live in format v1: depth.png is 0 (invalid) everywhere and coc.tif NaN everywhere, which the
reader accepts (``Pair.valid`` is all False). The f-number of the views is not in the files (EXIF is gone); the
paper's capture used a wide aperture against f/22, recorded here as ``f_number`` 4 by default (``--f-number``),
and the focus distance and focal length are unknown: they are written as placeholders the format needs (focus
1000 mm, focal length 50 mm) with ``"optics_known": false`` in params.json. So a DPDD import serves what needs no
depth: real test pairs for a DP deblurring network, and whether ``left + right`` matches the combined frame
(recorded per pair in ``"exposure"``); it is not a training set for RGBD -> DP, and ``dp5k evaluate`` (which renders
from depth and masks by it) leaves its pairs out.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from dp5k_common.errors import BadInputError

from .capture import Capture, Frames, SceneSource, same_size
from .exposure import measure_exposure

SENSOR_WIDTH_MM = 36.0
PLACEHOLDER_FOCUS_MM = 1000.0
PLACEHOLDER_FOCAL_MM = 50.0
SOURCE = "DPDD (Abuolaim & Brown, ECCV 2020, MIT), Canon EOS 5D Mark IV, DPP sRGB linearised; no depth"
_EXTS = (".png", ".PNG", ".tif", ".TIF", ".jpg", ".JPG")


def _find(folder: Path, stem: str) -> Path:
    for ext in _EXTS:
        if (folder / f"{stem}{ext}").is_file():
            return folder / f"{stem}{ext}"
    raise BadInputError(f"missing file {stem}.png", where=folder)


def _capture(root: Path, split: str, stem: str, f_number: float, curve: str, strict: bool) -> Iterator[Capture]:
    comb_p = _find(root / f"{split}_c" / "source", stem)
    sharp_p = _find(root / f"{split}_c" / "target", stem)
    left_p = _find(root / f"{split}_l" / "source", stem)
    right_p = _find(root / f"{split}_r" / "source", stem)
    fr = Frames(curve)
    comb, sharp = fr.read("c/source", comb_p), fr.read("c/target", sharp_p)
    left, right = fr.read("l/source", left_p), fr.read("r/source", right_p)
    H, W = same_size(comb_p.parent.parent.parent, **{comb_p.name + " (c/source)": comb, "c/target": sharp,
                                                      "l/source": left, "r/source": right})
    exp = measure_exposure(left, right, sharp, comb, where=str(comb_p))
    warns = fr.settle(left, right, sharp, comb, exp.combined_residual, strict, comb_p)
    lo, ro, so = exp.apply(left, right, sharp)
    yield Capture(scene=stem, sharp=so, left=lo, right=ro, depth_mm=np.zeros((H, W), np.float32), f_number=f_number,
                  focus_distance_mm=PLACEHOLDER_FOCUS_MM, focal_length_mm=PLACEHOLDER_FOCAL_MM,
                  pixel_pitch_mm=SENSOR_WIDTH_MM / W, camera="5d4", split=split,
                  extra={"source": SOURCE, "sharp_f_number": 22.0, "optics_known": False, "has_depth": False,
                         "exposure": exp.to_json(), "transfer_curve": curve, "bit_depth": fr.bits,
                         **({"input_warnings": warns} if warns else {})})


def dpdd_sources(src: str | os.PathLike[str], f_number: float = 4.0, curve: str = "srgb",
                 strict: bool = False) -> list[SceneSource]:
    """Scenes of a DPDD copy (module docstring), one pair each, in their own splits; ``strict``: inconsistent files
    (gray beside colour, 8 and 16-bit mixed, a curve that does not linearise) refuse the scene instead of a warning."""
    root = Path(src)
    if not root.is_dir():
        raise BadInputError("source folder not found", where=root)
    for cand in (root, root / "dd_dp_dataset_canon"):
        if any((cand / f"{s}_c" / "source").is_dir() for s in ("train", "val", "test")):
            root = cand
            break
    else:
        raise BadInputError("no {train,val,test}_c/source folder (expected the dd_dp_dataset_canon layout)", where=root)
    out = []
    for split in ("train", "val", "test"):
        folder = root / f"{split}_c" / "source"
        if not folder.is_dir():
            continue
        for p in sorted(q for q in folder.iterdir() if q.suffix in _EXTS and not q.name.startswith(".")):
            out.append(SceneSource(p.stem, p, lambda s=split, st=p.stem: _capture(root, s, st, float(f_number), curve, strict),
                                   split))
    if not out:
        raise BadInputError("no images in the {train,val,test}_c/source folders", where=root)
    return out
