"""What diagnose says about a named cause in a sentence (:func:`explanation`), and whether the data can show a colour
effect at all (:func:`colour_contrast`)."""

from __future__ import annotations

from typing import Any

import torch.nn.functional as F


from .data import Sample


EXPLAIN = {
    "lr_gain_imbalance": "the left and right views differ in brightness: L/R ratio {lr_ratio_center:.3f} at the centre, {lr_ratio_min:.3f}..{lr_ratio_max:.3f} over the field the fit pairs cover (x {field_x0:+.2f}..{field_x1:+.2f}, y {field_y0:+.2f}..{field_y1:+.2f})",
    "field_varying_psf": "the blur changes across the field: CoC grows by {coc_growth_at_corner:+.1%} at the corner, the split leaks {edge_leak:.3f} x |x| toward the edges, the split line moves {split_shift:+.2f} pupil radii per unit field x and the pupil is clipped {vignetting:+.2f} pupil radii per unit field radius along the field vector (cat's eye)",
    "chromatic_defocus": "the colour channels focus differently: focal length shift red {focal_shift_r_mm:+.4f} mm, blue {focal_shift_b_mm:+.4f} mm versus green",
    "disparity_scale": "the L/R disparity is {disparity_scale:.3f} x the ideal half-aperture disparity (crosstalk {crosstalk:.3f})",
    "focus_offset": "the lens focuses elsewhere than recorded: 1/F' = 1/({focus_factor:.3f} F) - {focus_shift_dpt:+.3f} dpt ({focus_offset_mm:+.0f} mm at the mean recorded distance)",
    "psf_profile": "the blur disc is not uniform: radial weight 1 {rim_gain2:+.2f} (rho/R)^2 {rim_gain:+.2f} (rho/R)^4",
    "front_back_asymmetry": "blur in front of focus differs from blur behind it: back rim gain {back_rim_gain:+.2f}, front centre gain {front_center_gain:+.2f}, front size x{front_size_factor:.3f}; spherical aberration {spherical_mm_f1:+.2f} mm at f/1 (zone CoC shift, / N^3)",
    "misregistration": "the views are shifted against the sharp image: left ({left_dx_px:+.2f}, {left_dy_px:+.2f}) px, right ({right_dx_px:+.2f}, {right_dy_px:+.2f}) px",
    "noise": "the views carry {variance_ratio:.1f} x the white-noise variance of a nominal sensor in flat regions: shot variance {shot_var:.2e} per unit intensity, read sigma {read_sigma:.2e}",
}


def explanation(name: str, params: dict[str, Any], held: tuple[str, ...] | list[str] = ()) -> str:
    """One sentence saying what ``name``'s fitted ``params`` mean (:data:`EXPLAIN`), and which parameters the
    fit data could not constrain."""
    try:
        text = EXPLAIN[name].format(**params)
    except (KeyError, ValueError):
        text = name
    if held:
        text += f" ({', '.join(held)} not fitted: too little of the fit data is where they act; held neutral)"
    return text


GREY_MAX_COLOUR_CONTRAST = 1e-3
"""Largest colour contrast (:func:`colour_contrast`, a variance ratio) at which the data counts as grey (R = G
= B within noise): colour effects are then not testable. Colour scenes measure far more (pooled over all
pairs: 0.15 on a 13-scene studio set, 0.94 on a 12-scene dp5k_testing/foreign_dp.py set); nominal sensor
noise alone (read sigma 1e-3, shot 2e-5 I at I = 0.5, independent per channel, averaged over 3 x 3) adds a
colour-difference variance of about 2e-6, 2e-4 of a texture variance of 1e-2."""


COLOUR_SMOOTH_PX = 3
"""Box window (px) that averages noise out of the images before their colour contrast is measured."""


def colour_contrast(samples: list[Sample]) -> float:
    r"""How much colour the data holds: over the scored pixels of ``sharp`` and of the views (each smoothed
    over :data:`COLOUR_SMOOTH_PX`), :math:`\sum_c (I_c - \bar I)^2 / \sum (\bar I - \langle \bar I \rangle)^2`
    with :math:`\bar I` the mean over R, G, B: the colour-difference variance per unit of luminance
    texture variance (dimensionless; 0 for grey data, the larger of the images')."""
    k = COLOUR_SMOOTH_PX
    worst = 0.0
    for key in ("sharp", "left", "right"):
        chroma = lum = 0.0
        for s in samples:
            img = getattr(s.batch, key)
            if img is None:
                continue
            img = F.avg_pool2d(F.pad(img.float(), (k // 2,) * 4, mode="replicate"), k, stride=1)
            m = s.score.float()
            y = img.mean(1, keepdim=True)
            n = m.sum().clamp(min=1.0)
            y_mean = (y * m).sum() / n
            chroma += float(((img - y) ** 2 * m).sum())
            lum += float(((y - y_mean) ** 2 * m).sum())
        if lum > 0:
            worst = max(worst, chroma / lum)
    return worst
