"""Statistical settings of diagnose's detectors and selection (:class:`DetectConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class DetectConfig:
    """Statistical settings of the detectors.

    Attributes:
        tile_px: tile side for the per-tile statistics.
        alpha: significance level of the one-sided tests.
        min_effect: smallest share of the base model's systematic error an effect must remove to count. It
            guards against mismatch between the model and the data (a real lens, another renderer) that an
            effect's component can absorb: on clean studio data no component explains more than 0.015, on
            the real Sdirt data components that are not the cause explain up to 0.33.
        min_effect_by_effect: per-effect thresholds that replace ``min_effect``. ``chromatic_defocus``: 0.04.
            Its component only moves the red and blue channels' focus against green, so mismatch that is the
            same in every colour channel, as a real lens' PSF shape is, cannot feed it: on the real Sdirt
            data achromatic components explain 0.14-0.33 without being the cause, chromatic_defocus -0.006;
            on 26 clean studio sets it explains at most 0.001. A strength-1 studio focal shift (0.1-0.4 px
            of CoC) explains 0.04-0.24 (docs/diagnose.md, Detectability).
        base_lm_iters: Levenberg-Marquardt iterations of the base model's own fit (rim softness and gain),
            which every effect is measured against; it must converge, or the effects' fits, which refit the
            rim, are credited with the rest of its convergence.
        noise_min_effect: smallest excess noise variance, as a multiple of the nominal variance, that counts
            as ``noise`` (0.5: 1.5 x the nominal variance; clean studio data measures 0.04-0.06).
        systematic_floor: the systematic error is at least this share of a model's squared error (bounds effect
            sizes where the measured noise explains nearly all of it). About twice the uncertainty of the noise
            estimate (the views' noise ratio is measured to 2-3 % from thousands of flat pixels); 0.2 until
            2026-11-27, before the sharp frame's noise was counted as noise: on another renderer's clean set
            with a noisy f/22 ``sharp`` the views' and the sharp frame's noise are 96 % of the base model's
            squared error (30.9 of 32.3 units), so a floor of 0.2 x the error stood for 4.6 x the systematic
            error, and a planted field-varying PSF (named now at 0.17 of what is left without it) was not
            even screened.
        remaining_floor: an effect's size is a share of the systematic error the model without it leaves, but
            of at least this share of the base model's systematic error (what little several effects leave is
            not a scale to measure a further one on) or the nominal sensor's noise energy on the same pixels,
            whichever is smaller (a remainder as large as a healthy sensor's noise is a scale real captures
            have; :func:`dp5k_diagnose.selection.least_systematic`).
        noise_flat_window_px, noise_flat_quantile: the window over which sharp must be flat, and the
            flattest fraction of valid pixels used to measure noise.
        nominal_shot_var, nominal_read_sigma: the noise a healthy sensor is expected to show (linear
            units: a ~50 000 e- full well scaled to [0, 1] and a read noise of 1e-3); only noise beyond
            it counts as the ``noise`` effect.
    """

    tile_px: int = 32
    alpha: float = 0.05
    min_effect: float = 0.15
    min_effect_by_effect: dict[str, float] = field(default_factory=lambda: {"chromatic_defocus": 0.04})
    base_lm_iters: int = 12
    noise_min_effect: float = 0.5
    noise_flat_window_px: int = 13
    noise_flat_quantile: float = 0.10
    nominal_shot_var: float = 2.0e-5
    nominal_read_sigma: float = 1.0e-3
    systematic_floor: float = 0.05
    remaining_floor: float = 0.05

    def threshold(self, effect: str) -> float:
        """The effect size ``effect`` must exceed to be detected (share of the systematic error; ``noise``:
        excess variance ratio)."""
        if effect == "noise":
            return self.noise_min_effect
        return float(self.min_effect_by_effect.get(effect, self.min_effect))


@dataclass
class SelectConfig:
    """Settings of the selection of causes (:func:`dp5k_diagnose.selection.select_causes`).

    Attributes:
        screen_share: an effect enters the full model when one Gauss-Newton step from the fitted base model
            predicts that it removes at least this fraction of its detection threshold
            (:meth:`DetectConfig.threshold`) of the fit crops' systematic error, alone or as its unique part of
            the joint step of every effect. A first-order screen; the held-out tests decide.
        full_lm_iters: Levenberg-Marquardt iterations of the full model (every screened effect at once).
        rescreens: times the effects left out of the confirmed model are screened again around it (a first-order
            screen around the base model underrates an effect whose signal another effect's larger error hides,
            and an effect can be masked by one the elimination later removed); when one passes that the last
            full model did not hold, the confirmed causes and every passing effect make a new full model, which
            is eliminated and confirmed in turn.
        refit_lm_iters: iterations of each refit that confirms a selection (the final model, the model
            without each cause, a look-alike swapped in).
        lookalike_corr: effects whose Jacobians' largest canonical correlation on the fit crops (nuisance
            parameters projected out) reaches this are tried in each other's place.
        lookalike_loss: an effect swapped in for a named cause is its look-alike when the detection pairs'
            preference for the cause is not significant or smaller than this share of the cause's threshold
            (of the systematic error the swapped model leaves).
        lookalike_tries: at most this many effects (the most correlated first) are tried in a cause's place.
        prescreen_margin: before each re-screen, the effects left out are screened at first order with the
            last screen's Jacobian columns (measured around an earlier model) and the confirmed model's exact
            residual; when none reaches this fraction of the screen's bar (``screen_share`` of its threshold),
            the re-screen, which renders a Jacobian column per parameter, is not run and the selection ends.
            0 always runs it.
    """

    screen_share: float = 0.5
    full_lm_iters: int = 5
    rescreens: int = 2
    refit_lm_iters: int = 2
    lookalike_corr: float = 0.9
    lookalike_loss: float = 0.25
    lookalike_tries: int = 2
    prescreen_margin: float = 0.25
