"""The batch every simulator consumes: sharp image, signed CoC, depth, validity and the imaging params."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from dp5k_common.dataset import Pair


def frame_field(origin: tuple[int, int], full_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """(2, H, W) float32 field coordinates (x, y) in [-1, 1] of an (W, H) ``size`` region whose top-left pixel is
    ``origin`` (x0, y0) in a frame of ``full_size`` (W_f, H_f), the frame's centre at 0 (the convention of
    ``neural_dp.simulators.base.field.field_coords``).

    >>> frame_field((0, 0), (3, 3), (3, 1))[0].tolist()
    [[-1.0, 0.0, 1.0]]
    """
    (x0, y0), (Wf, Hf), (W, H) = origin, full_size, size
    xs = (np.arange(W, dtype=np.float64) + x0 - (Wf - 1) / 2) / max((Wf - 1) / 2, 0.5)
    ys = (np.arange(H, dtype=np.float64) + y0 - (Hf - 1) / 2) / max((Hf - 1) / 2, 0.5)
    return np.stack([np.broadcast_to(xs[None, :], (H, W)), np.broadcast_to(ys[:, None], (H, W))]).astype(np.float32)


@dataclass
class DPBatch:
    """A batch of B pairs' simulator inputs (and, when known, the measured views).

    Attributes:
        sharp: (B, 3, H, W) float, linear, [0, 1].
        coc_px: (B, 1, H, W) float, signed CoC diameter in output pixels (Eq. 6); 0 where invalid.
        depth_mm: (B, 1, H, W) float, millimetres; 0 where invalid.
        valid: (B, 1, H, W) bool, depth valid.
        f_number: (B,) float.
        focus_distance_mm: (B,) float.
        focal_length_mm: (B,) float, thin-lens.
        pixel_pitch_mm: (B,) float, of the output image.
        focus_point_px: (B, 2) float, (x, y).
        left: (B, 3, H, W) measured left view, or None.
        right: (B, 3, H, W) measured right view, or None.
        pair_ids: the pairs' ids, length B.
        sharp_f_number: (B,) float, the f-number of ``sharp`` (params.json ``sharp_f_number``, format v1
            default 22; 0 = an all-in-focus image), or None (all 22).
        field: (B, 2, H, W) float, where each pixel sits in its camera frame, (x, y) in [-1, 1] with the frame's
            centre at 0 (a tile's from its ``crop_origin_px`` / ``full_image_size``; a mirrored item's x negated),
            or None (every item is a whole frame).
        prior_left, prior_right: (B, 3, H, W) the physical model's views of these items, when a trainer rendered
            them beforehand (``neural_dp``: rendered once per whole pair, then cropped and augmented with the
            item), or None (a simulator that needs them renders them).
        mirrored: (B,) bool, items mirrored left-right with their views swapped (a training augmentation), or
            None (none is).
    """

    sharp: Tensor
    coc_px: Tensor
    depth_mm: Tensor
    valid: Tensor
    f_number: Tensor
    focus_distance_mm: Tensor
    focal_length_mm: Tensor
    pixel_pitch_mm: Tensor
    focus_point_px: Tensor
    left: Tensor | None = None
    right: Tensor | None = None
    pair_ids: tuple[str, ...] = ()
    sharp_f_number: Tensor | None = None
    field: Tensor | None = None
    prior_left: Tensor | None = None
    prior_right: Tensor | None = None
    mirrored: Tensor | None = None

    @classmethod
    def from_pairs(cls, pairs: Sequence[Pair], device: torch.device | str = "cpu") -> DPBatch:
        """Stack loaded pairs (all of one image size) into a batch on ``device``."""
        def img(a: np.ndarray) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))

        valid = [p.valid for p in pairs]
        return cls(
            sharp=torch.stack([img(p.sharp) for p in pairs]).to(device),
            coc_px=torch.stack([torch.from_numpy(np.where(v, p.coc_px, 0).astype(np.float32))[None] for p, v in zip(pairs, valid)]).to(device),
            depth_mm=torch.stack([torch.from_numpy(np.where(v, p.depth_mm, 0).astype(np.float32))[None] for p, v in zip(pairs, valid)]).to(device),
            valid=torch.stack([torch.from_numpy(v)[None] for v in valid]).to(device),
            f_number=torch.tensor([p.params.f_number for p in pairs], dtype=torch.float32, device=device),
            focus_distance_mm=torch.tensor([p.params.focus_distance_mm for p in pairs], dtype=torch.float32, device=device),
            focal_length_mm=torch.tensor([p.params.focal_length_mm for p in pairs], dtype=torch.float32, device=device),
            pixel_pitch_mm=torch.tensor([p.params.pixel_pitch_mm for p in pairs], dtype=torch.float32, device=device),
            focus_point_px=torch.tensor([p.params.focus_point_px for p in pairs], dtype=torch.float32, device=device),
            left=torch.stack([img(p.left) for p in pairs]).to(device),
            right=torch.stack([img(p.right) for p in pairs]).to(device),
            pair_ids=tuple(p.pair_id for p in pairs),
            sharp_f_number=torch.tensor([p.params.sharp_f_number for p in pairs], dtype=torch.float32, device=device),
            field=torch.stack([torch.from_numpy(frame_field(*p.params.frame_geometry, p.valid.shape[::-1])) for p in pairs]).to(device),
        )

    def to(self, device: torch.device | str) -> DPBatch:
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to(device) if isinstance(v, Tensor) else v
        return DPBatch(**out)

    def crop(self, y0: int, x0: int, h: int, w: int) -> DPBatch:
        """A spatial crop of every image tensor; ``focus_point_px`` is shifted into crop coordinates."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, Tensor) and v.ndim == 4:
                v = v[..., y0 : y0 + h, x0 : x0 + w]
            out[f.name] = v
        out["focus_point_px"] = self.focus_point_px - torch.tensor([x0, y0], dtype=self.focus_point_px.dtype, device=self.focus_point_px.device)
        return DPBatch(**out)
