"""Raw route: Dual Pixel RAW layout, and flat-patch mean/variance against the sensor model."""

from __future__ import annotations

import numpy as np
import pytest

from dp5k_studio import DEFAULT_SENSOR, EffectSet, Studio, make_rig, plane_scene
from dp5k_studio.sensor import bayer_channel_index
from dp5k_studio.textures import TextureSpec


def _flat_studio(effects: EffectSet | None = None, seed: int = 0) -> Studio:
    tex = TextureSpec("flat", color_a=(0.5, 0.5, 0.5))
    return Studio(plane_scene(2.0, tex), make_rig(20), effects, seed=seed, supersample=1)


@pytest.mark.parametrize("iso,shutter_s", [(100, 1 / 100), (800, 1 / 400)])
def test_flat_patch_mean_and_variance_follow_the_sensor_model(iso: int, shutter_s: float) -> None:
    st = _flat_studio()
    N = 4.0
    raw = st.expose(0, N, 2.0, shutter_s, iso, rng=np.random.default_rng(1))
    rad = st.radiance(0)
    s = DEFAULT_SENSOR
    g = s.gain_e_per_dn(iso)
    sig_r = s.read_sigma_dn(iso)
    H, W = raw.main.shape
    ch = bayer_channel_index(H, W)
    inner = np.zeros((H, W), bool)
    inner[20:-20, 20:-20] = True
    for c in range(3):
        m = inner & (ch == c)
        lam = float(rad[m, c].mean()) * s.qe_rgb[c] * s.q_e_per_s * shutter_s / N**2  # electrons, full pixel
        main = raw.main[m].astype(np.float64) - s.black_level
        aux = raw.aux[m].astype(np.float64) - s.black_level
        assert main.mean() == pytest.approx(lam / g, rel=0.01)
        assert aux.mean() == pytest.approx(lam / 2 / g, rel=0.01)  # in focus: the left photodiode has half
        assert main.var() == pytest.approx(lam / g**2 + sig_r**2 + 1 / 12, rel=0.12)
        assert aux.var() == pytest.approx(lam / 2 / g**2 + sig_r**2 + 1 / 12, rel=0.12)


def test_raw_layout_and_metadata() -> None:
    st = _flat_studio()
    raw = st.expose(1, 1.8, 2.0, 1 / 100, 100)
    assert raw.main.dtype == np.uint16 and raw.aux.dtype == np.uint16
    assert raw.main.shape == (224, 336) == raw.aux.shape
    assert raw.white_level == 16383 and raw.black_level == 512
    assert raw.main.max() <= 16383
    assert raw.metadata["aux_view"] == "left" and raw.metadata["camera"] == "cam1"
    # main - aux is the right photodiode: same level as aux in focus
    assert raw.right().mean() == pytest.approx((raw.aux.astype(float) - raw.black_level).mean(), rel=0.02)
    assert raw.wb_gains[1] == 1.0 and raw.wb_gains[0] > 1.0 and raw.wb_gains[2] > 1.0


def test_noise_effect_raises_variance_not_mean() -> None:
    nom = _flat_studio().expose(0, 4.0, 2.0, 1 / 100, 100, rng=np.random.default_rng(2))
    eff = _flat_studio(EffectSet.of(noise=1.0)).expose(0, 4.0, 2.0, 1 / 100, 100, rng=np.random.default_rng(2))
    ch = bayer_channel_index(*nom.main.shape)
    m = np.zeros(nom.main.shape, bool)
    m[20:-20, 20:-20] = True
    m &= ch == 1
    a = nom.main[m].astype(float)
    b = eff.main[m].astype(float)
    assert b.mean() == pytest.approx(a.mean(), rel=0.005)
    assert b.var() / a.var() == pytest.approx(4.0, rel=0.2)  # shot-dominated: x (1 + 3 s)


def test_f22_frame_is_sharper_than_f18() -> None:
    from dp5k_studio import make_scene

    rig = make_rig(20)
    st = Studio(make_scene("boxes"), rig, supersample=1)
    F = st.focus_distance_m(0, st.focus_point_px(0))
    sharp = st.render_views(0, 22.0, F)
    blur = st.render_views(0, 1.8, F)
    grad = lambda a: float(np.abs(np.diff((a.left + a.right)[:, :, 1], axis=1)).mean())  # noqa: E731
    assert grad(sharp) > 1.3 * grad(blur)
