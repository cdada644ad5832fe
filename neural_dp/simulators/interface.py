"""The one interface every DP simulator implements."""

from __future__ import annotations

from typing import ClassVar

from torch import Tensor, nn

from dp5k_learn.batch import DPBatch


class DPSimulator(nn.Module):
    """Given a sharp image, signed CoC, depth with its valid mask and the pair's params, return the DP views.

    Subclasses implement :meth:`forward`. ``forward(batch)`` returns ``(left, right)``, each (B, 3, H, W)
    linear, on the batch's device, on the dataset's scale (ideally left + right = full-aperture blur).
    Pixels with invalid depth may hold anything; every metric masks them out.

    Models with parameters to fit from data (the base model's gain and rim softness) override
    :meth:`fit`; the peers keep their published defaults and do not.
    """

    name: ClassVar[str] = "abstract"

    def forward(self, batch: DPBatch) -> tuple[Tensor, Tensor]:  # pragma: no cover - interface
        raise NotImplementedError

    def fit(self, batches: list[DPBatch]) -> dict[str, float]:
        """Fit this simulator's free parameters on training batches; return them by name. Default: none."""
        return {}
