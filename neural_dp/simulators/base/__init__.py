"""The physical base model: the ideal thin-lens DP model, occlusion-aware, with two fitted parameters.

Each DP view integrates exactly one half of the aperture (a hard split through the disc centre); the
right PSF is the hflip of the left (Eq. 2). For ``coc > 0`` (behind focus) the left view's light lands on
the left half of the disc (docs/conventions.md), mirrored for ``coc < 0``. The only free parameters are
the softness of the disc's rim (``rim_softness_px``) and an overall ``gain``::

    I_l = gain * H_l(|c|, s) * I_s / 2,   I_r = gain * hflip(H_l) * I_s / 2,   sum H_l = 1

Rendering from RGBD is layered and occlusion-aware: the signed CoC range is cut into nodes (soft, linear
assignment of each pixel to its two neighbouring nodes); each node's premultiplied colour and alpha are
blurred with that node's half-disc PSF (FFT), composited front to back (near = most negative CoC first,
since CoC grows monotonically with depth), and normalised by the accumulated coverage (no dark seams at
depth edges or image borders).

Effects the base model lacks (L/R gain imbalance, field dependence, colour dependence, ...) are added as
:class:`Component` objects: each may change the per-channel CoC map, the per-node PSF shape (per colour
channel and field radius) or the rendered views, and carries its own parameters fitted on training data.
:mod:`.components` holds the components of the effect vocabulary (``dp5k_common.effects``), which
``dp5k diagnose`` detects and fits.

The package, one job per module: :mod:`.psf` (half-disc kernels and their cache), :mod:`.render` (the
occlusion-aware layered renderer), :mod:`.sharp` (undoing the sharp frame's own blur), :mod:`.model`
(``BaseModel`` and ``Component``), :mod:`.fit` (the Levenberg-Marquardt fitter), :mod:`.field` (field
coordinates of crops).
"""

from .field import field_coords, field_r2
from .fit import fit_parameters
from .model import FIELD_NODES_R2, BaseModel, Component
from .psf import PSFShape, half_disc_kernels
from .render import RenderConfig, render_layers
from .sharp import sharp_blur_coc_px, sharp_radiance

__all__ = ["PSFShape", "Component", "RenderConfig", "BaseModel", "half_disc_kernels", "field_coords", "field_r2", "fit_parameters",
           "render_layers", "sharp_radiance", "sharp_blur_coc_px", "FIELD_NODES_R2"]
