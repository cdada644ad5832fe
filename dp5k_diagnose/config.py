"""The settings of one diagnosis (:class:`DiagnoseConfig`), passed down once from the command to every step."""

from __future__ import annotations

from dataclasses import dataclass, field

from dp5k_common.effects import EFFECT_NAMES

from .neural_reach import NeuralReachConfig


@dataclass
class DiagnoseConfig:
    """Settings of one ``dp5k diagnose``.

    Attributes:
        seed: seeds the fit crops, the atlas's pixel draws, the model's matched noise and every bootstrap.
        alpha: level of the signature tests (each effect's values Bonferroni-corrected among themselves).
        n_boot: bootstrap resamples over pairs (the atlas, the signatures) and over tiles (the gains).
        nominal_shot_var, nominal_read_sigma: the noise a healthy sensor is expected to show in the views (linear
            units: variance = shot_var I + read_sigma^2); only noise beyond it is the ``noise`` effect.
        noise_min_ratio: the views' noise variance over the nominal from which ``noise`` is named (1.5).
        fit_pairs: at most this many train pairs' crops fit the models (None: every train pair); the default is what
            ``--fit-pairs auto`` gives (the atlas reads every pair whatever it is).
        crop_px: side of the fit crops (whole images when smaller).
        crops_per_pair: crops per fit pair when the images are larger than ``crop_px``.
        base_lm_iters: Levenberg-Marquardt iterations of the base model's own fit (rim softness, gain, pixel
            sampling): it must converge, or a cause is credited with the rest of its convergence.
        cause_lm_iters: iterations of each extended model's fit (the named causes and the candidate together).
        max_causes: the most causes one diagnosis names.
        tile_px: tile side of the held-out gains' bootstrap (tiles resampled within each held-out pair).
        effects: the effects that may be named (default: the whole vocabulary).
        sharp_f_number: how to read ``sharp`` in pairs whose params.json does not state ``sharp_f_number``: None =
            choose between f/22 and all-in-focus by the base fit's error, else that f-number (0 = all-in-focus).
        threads: PyTorch intra-op threads while diagnosing (restored after; 0 = leave as set): renders of a few
            hundred px barely profit from more, and where cores are shared, waiting threads slow them down.
        neural: the Neural DP extension study's settings (``--simulator neural:CKPT``).
    """

    seed: int = 0
    alpha: float = 0.05
    n_boot: int = 200
    nominal_shot_var: float = 2.0e-5
    nominal_read_sigma: float = 1.0e-3
    noise_min_ratio: float = 1.5
    fit_pairs: int | None = 8
    crop_px: int = 96
    crops_per_pair: int = 2
    base_lm_iters: int = 12
    cause_lm_iters: int = 6
    max_causes: int = 5
    tile_px: int = 32
    effects: tuple[str, ...] = EFFECT_NAMES
    sharp_f_number: float | None = None
    threads: int = 1
    neural: NeuralReachConfig = field(default_factory=NeuralReachConfig)
