"""The second independent DP renderer (dp5k_testing/aperture_dp.py): a sub-aperture gather with z-buffer occlusion.

Its physics is checked against the thin lens, not against dp5k: point sources give the half-disc centroids
(docs/conventions.md), each planted effect moves the views the way its physics says, a near plane hides a far
one per sub-aperture view, the noise follows its stated model, and the writer's output is format v1.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dp5k_common.dataset import DatasetReader
from dp5k_testing.aperture_dp import (
    EFFECT_DEFAULTS,
    INTERPOLATION_VARIANCE_PX2,
    NOMINAL_READ_SIGMA,
    NOMINAL_SHOT_VAR,
    ApertureSamples,
    Effects,
    Lens,
    add_sensor_noise,
    aperture_samples,
    render_sharp,
    render_views,
    views_noise,
    write_dataset,
    write_matrix_cell,
)
from dp5k_testing.aperture_scene import TEXELS_PER_PX, Layer, LayeredScene, point_scene

SIZE = (96, 64)
PITCH = 17.3 / 256  # the 256 px frame's pitch (mm): CoCs of a few px
LENS = Lens(35.0, 1.8, 1000.0, PITCH)
SAMPLES = aperture_samples(256, np.random.default_rng(0))


def moments(img: np.ndarray, ch: int = 1) -> tuple[float, float, float, float, float]:
    """(centroid x, centroid y, variance x, variance y, total) of channel ``ch`` of an (H, W, 3) image, px."""
    w = img[..., ch].astype(np.float64)
    yy, xx = np.mgrid[0 : w.shape[0], 0 : w.shape[1]]
    s = w.sum()
    cx, cy = (w * xx).sum() / s, (w * yy).sum() / s
    return cx, cy, (w * (xx - cx) ** 2).sum() / s, (w * (yy - cy) ** 2).sum() / s, s


def point_views(z_mm: float, effects: Effects | str = "none", at: tuple[float, float] = (47.0, 31.0),
                lens: Lens = LENS) -> tuple[np.ndarray, np.ndarray]:
    eff = effects if isinstance(effects, Effects) else Effects.of(effects)
    return render_views(point_scene(SIZE, 24, at, z_mm), lens, eff, np.random.default_rng(0), samples=SAMPLES)


@pytest.mark.parametrize("z_mm", [560.0, 760.0, 1300.0, 2500.0])
def test_ideal_lens_gives_the_thin_lens_dp_disparity(z_mm: float) -> None:
    """L - R centroid separation of a point = the half discs' 8 R / (3 pi) = 4 c / (3 pi) (within 1 %), with the
    sign of docs/conventions.md: behind focus the left view holds the left half of the disc."""
    c = float(LENS.coc_px(np.float64(z_mm)))
    left, right = point_views(z_mm, at=(47.5, 31.0))  # the frame's centre column
    (lx, ly, *_), (rx, ry, *_) = moments(left), moments(right)
    assert rx - lx == pytest.approx(4 * c / (3 * math.pi), rel=0.01)
    assert np.sign(47.5 - lx) == np.sign(c)  # behind focus (c > 0) the left view's light is left of the point
    assert ly == pytest.approx(31.0, abs=0.01) and ry == pytest.approx(31.0, abs=0.01)
    np.testing.assert_allclose(right, left[:, ::-1], atol=1e-5)  # R = hflip(L) about the point (Eq. 2)


@pytest.mark.parametrize("z_mm", [640.0, 2500.0])
def test_left_plus_right_is_the_full_disc_and_each_view_a_half_disc(z_mm: float) -> None:
    """Against the in-focus point: L + R adds a flat disc's second moment R^2 / 4 in x and y; each view adds
    R^2 / 4 - (4 R / 3 pi)^2 in x (a half disc) and R^2 / 4 in y; the light is conserved. (Plus the bilinear
    reading's known 1/24 px^2 for defocused light, INTERPOLATION_VARIANCE_PX2.)"""
    R = abs(float(LENS.coc_px(np.float64(z_mm)))) / 2
    l0, r0 = point_views(1000.0)
    left, right = point_views(z_mm)
    m0, m = moments(l0 + r0), moments(left + right)
    assert m[2] - m0[2] == pytest.approx(R * R / 4 + INTERPOLATION_VARIANCE_PX2, rel=0.02)
    assert m[3] - m0[3] == pytest.approx(R * R / 4 + INTERPOLATION_VARIANCE_PX2, rel=0.02)
    assert m[4] == pytest.approx(m0[4], rel=1e-4)
    h0, h = moments(l0), moments(left)
    assert h[2] - h0[2] == pytest.approx(R * R / 4 - (4 * R / (3 * math.pi)) ** 2 + INTERPOLATION_VARIANCE_PX2, rel=0.03)
    assert h[3] - h0[3] == pytest.approx(R * R / 4 + INTERPOLATION_VARIANCE_PX2, rel=0.02)


def test_each_effect_changes_the_views_the_way_its_physics_says() -> None:
    z_back, z_front = 2500.0, 640.0  # c = +6.3 and -5.6 px at f/1.8
    ideal_back = point_views(z_back)
    sep = lambda lr, ch=1: moments(lr[1], ch)[0] - moments(lr[0], ch)[0]  # noqa: E731

    # disparity_scale: a soft split lowers the disparity (to 0.58-0.70 of the ideal at its default) and keeps L + R
    soft = point_views(z_back, "disparity_scale")
    assert 0.55 < sep(soft) / sep(ideal_back) < 0.72
    np.testing.assert_allclose(soft[0] + soft[1], ideal_back[0] + ideal_back[1], atol=1e-5)

    # focus_offset: the lens focuses beyond the recorded distance (1/F - 0.08 D), so a point at the recorded
    # focus is in front of the true focus by Eq. 6 at F_true, and a point at F_true is sharp
    F_true = 1.0 / (1.0 / 1000.0 - EFFECT_DEFAULTS["focus_offset"] / 1000.0)
    c_true = float(Lens(35.0, 1.8, F_true, PITCH).coc_px(np.float64(1000.0)))
    assert c_true < -0.5
    assert sep(point_views(1000.0, "focus_offset")) == pytest.approx(4 * c_true / (3 * math.pi), rel=0.02)
    assert abs(sep(point_views(F_true, "focus_offset"))) < 0.01

    # chromatic_defocus: red (longer focal length) focuses behind the sensor, blue in front: at the green focus
    # red has the disparity of a point in front of focus, blue of one behind, green none
    chrom = point_views(1000.0, "chromatic_defocus")
    a = EFFECT_DEFAULTS["chromatic_defocus"]
    for ch, f_c in ((0, 35.0 * (1 + a)), (2, 35.0 * (1 - 1.3 * a))):
        c0, c1 = LENS.coc_coefficients(channel_focal_length_mm=f_c)
        assert sep(chrom, ch) == pytest.approx(4 * (c0 + c1 / 1000.0) / (3 * math.pi), rel=0.03)
    assert sep(chrom, 0) < -0.2 and sep(chrom, 2) > 0.2 and abs(sep(chrom, 1)) < 1e-6

    # psf_profile: a bright ring near the rim moves light outward: larger disparity and disc, same total
    ring = point_views(z_back, "psf_profile")
    assert sep(ring) > 1.08 * sep(ideal_back)
    assert moments(ring[0] + ring[1])[3] > 1.15 * moments(ideal_back[0] + ideal_back[1])[3]

    # front_back_asymmetry: spherical aberration makes the disc in front of focus larger than behind it, at equal
    # |CoC| (the ideal lens's are equal); DP autofocus keeps the disparity at the focus distance at zero
    fb = lambda eff: moments(sum(point_views(z_front, eff)))[3] / moments(sum(point_views(z_back, eff)))[3]  # noqa: E731
    assert fb("front_back_asymmetry") > 1.08 * fb("none")
    assert abs(sep(point_views(1000.0, "front_back_asymmetry"))) < 0.01

    # field_varying_psf: cat's-eye vignetting narrows a defocused point's disc along the field direction, more the
    # farther off axis, and the per-view shading correction keeps an in-focus point's L / R at 1
    edge = (88.0, 31.0)
    var_x = lambda lr: moments(lr[0] + lr[1])[2]  # noqa: E731
    narrowing_edge = var_x(point_views(z_back, at=edge)) - var_x(point_views(z_back, "field_varying_psf", at=edge))
    narrowing_centre = var_x(ideal_back) - var_x(point_views(z_back, "field_varying_psf"))
    assert narrowing_edge > 0.3 and 0 <= narrowing_centre < 0.3 * narrowing_edge
    in_focus = point_views(1000.0, "field_varying_psf", at=edge)
    assert moments(in_focus[0])[4] / moments(in_focus[1])[4] == pytest.approx(1.0, abs=1e-3)

    # misregistration: both views move by (0.6, -0.35) px against the scene (rotation ~0 at the centre)
    ml, mr = point_views(1000.0, "misregistration")
    for v in (ml, mr):
        x, y, *_ = moments(v)
        assert x - 47.0 == pytest.approx(0.6, abs=0.02) and y - 31.0 == pytest.approx(-0.35, abs=0.02)


def test_lr_gain_ramp_changes_the_brightness_ratio_across_the_field_and_keeps_the_sum() -> None:
    scene = LayeredScene([Layer(np.full(((SIZE[1] + 16) * TEXELS_PER_PX, (SIZE[0] + 16) * TEXELS_PER_PX, 4), 0.5, np.float32),
                                (1 / 1000.0, 0.0, 0.0))], SIZE, 8, (47, 31))
    left, right = render_views(scene, LENS, Effects.of("lr_gain_imbalance"), np.random.default_rng(0), samples=SAMPLES)
    ratio = left[..., 1] / right[..., 1]
    assert ratio[-1].mean() > 1.15 and ratio[0].mean() < 1.0  # bottom L brighter, top slightly R brighter
    assert ratio[32, 0] > ratio[32, 47] < ratio[32, 95]  # quadratic in x
    np.testing.assert_allclose(left + right, 0.5, atol=1e-5)


def test_a_near_plane_hides_a_far_one_in_every_sub_aperture_view() -> None:
    """A blue plane in focus behind a green card 5.6 px of CoC in front of focus: through every lens point the
    card covers the plane completely where it lands (no blue light on it), and the combined view shows what
    occlusion does at a defocused edge: blue light seen around the card just inside its silhouette, none at
    its centre."""
    W, H = SIZE
    pad = 16
    ht, wt = (H + 2 * pad) * TEXELS_PER_PX, (W + 2 * pad) * TEXELS_PER_PX
    blue = np.zeros((ht, wt, 4), np.float32)
    blue[..., 2] = blue[..., 3] = 1.0
    card = np.zeros((ht, wt, 4), np.float32)
    card[..., 1] = 1.0
    x0 = (pad + 30) * TEXELS_PER_PX  # the card covers frame x >= 30 (its left edge) ...
    card[(pad + 10) * TEXELS_PER_PX : (pad + 54) * TEXELS_PER_PX, x0 : (pad + 90) * TEXELS_PER_PX, 3] = 1.0
    scene = LayeredScene([Layer(blue, (1 / 1000.0, 0.0, 0.0)), Layer(card, (1 / 640.0, 0.0, 0.0))], SIZE, pad, (10, 31))
    c = float(LENS.coc_px(np.float64(640.0)))
    for u, v in ((0.9, 0.0), (-0.9, 0.0), (0.0, 0.9), (0.5, -0.5), (0.0, 0.0)):
        one = ApertureSamples(np.array([u, -u]), np.array([v, v]))
        left, right = render_views(scene, LENS, Effects.of("none"), np.random.default_rng(0), samples=one)
        view = left + right  # this lens point and its mirror image, each in one view
        shift = -u * c / 2  # where the card's edge lands through lens point u (the mirror lands at +u c / 2)
        inside = slice(int(math.ceil(30 + abs(shift))) + 1, 80)
        assert view[20:44, inside, 1].min() > 0.99 and view[20:44, inside, 2].max() < 1e-6
    left, right = render_views(scene, LENS, Effects.of("none"), np.random.default_rng(0), samples=SAMPLES)
    view = left + right
    assert view[31, 31, 2] > 0.1  # 1 px inside the card's edge, part of the aperture sees the plane around it
    assert view[31, 60, 2] < 1e-6 and view[31, 60, 1] > 0.999  # deep inside: only the card
    assert view[31, 29, 1] > 0.1  # 1 px outside: the card's blur reaches over the plane


@pytest.mark.parametrize("level", [0.1, 0.5])
def test_noise_follows_the_stated_shot_and_read_model(level: float) -> None:
    img = np.full((200, 200, 3), level, np.float32)
    noisy = add_sensor_noise(np.random.default_rng(1), img, NOMINAL_SHOT_VAR, NOMINAL_READ_SIGMA)
    assert float((noisy - img).var()) == pytest.approx(NOMINAL_SHOT_VAR * level + NOMINAL_READ_SIGMA**2, rel=0.02)
    shot, read = views_noise(Effects.of("noise"), NOMINAL_SHOT_VAR, NOMINAL_READ_SIGMA)
    a = EFFECT_DEFAULTS["noise"]
    assert (shot, read) == pytest.approx((NOMINAL_SHOT_VAR * (1 + a), NOMINAL_READ_SIGMA * (1 + a / 2)))


def test_the_writer_adds_nominal_noise_to_views_and_sharp(tmp_path: Path) -> None:
    """Same seed with and without noise: the first pair's scene and rendering are the same, so the difference
    of the written images is the noise; its variance matches the model at the noise-free intensities."""
    kw = dict(scenes=3, size=(64, 44), f_numbers=(1.8,), seed=4)
    write_dataset(tmp_path / "noisy", "none", **kw)
    write_dataset(tmp_path / "clean", "none", noise=False, **kw)
    pid = DatasetReader(tmp_path / "clean").ids("train")[0]
    noisy, clean = DatasetReader(tmp_path / "noisy").load(pid), DatasetReader(tmp_path / "clean").load(pid)
    for name in ("left", "right", "sharp"):
        n, c = getattr(noisy, name).astype(np.float64), getattr(clean, name).astype(np.float64)
        ratio = ((n - c) ** 2).mean() / (NOMINAL_SHOT_VAR * c + NOMINAL_READ_SIGMA**2).mean()
        assert ratio == pytest.approx(1.0, abs=0.06), name


def test_the_writer_writes_format_v1_with_the_planted_effects_only_in_planted_json(tmp_path: Path) -> None:
    out = write_matrix_cell(tmp_path / "cell", "lr_gain_imbalance+psf_profile", strength=0.5, seed=2, size=(48, 32), pairs=6)
    reader = DatasetReader(out)
    assert {s: len(reader.ids(s)) for s in ("train", "val", "test")} == {"train": 2, "val": 2, "test": 2}
    scenes = {s: {reader.params(p).scene for p in reader.ids(s)} for s in ("train", "val", "test")}
    assert not (scenes["train"] & scenes["val"] or scenes["train"] & scenes["test"] or scenes["val"] & scenes["test"])
    pair = reader.load(reader.ids("test")[0])
    p = pair.params
    assert p.sharp_f_number == 22 and p.image_size == (48, 32) and p.f_number in (1.8, 4.0)
    c = p.focal_length_mm**2 * (pair.depth_mm - p.focus_distance_mm) / (p.f_number * pair.depth_mm * (p.focus_distance_mm - p.focal_length_mm))
    np.testing.assert_allclose(pair.coc_px, c / p.pixel_pitch_mm, rtol=1e-4, atol=1e-4)  # Eq. 6
    planted = json.loads((out / "planted.json").read_text())
    assert planted["effects"] == pytest.approx({"lr_gain_imbalance": 0.5 * EFFECT_DEFAULTS["lr_gain_imbalance"],
                                                "psf_profile": 0.5 * EFFECT_DEFAULTS["psf_profile"]})
    text = (out / "dataset.json").read_text() + "".join((reader.pair_dir(i) / "params.json").read_text() for i in reader.ids())
    assert "lr_gain" not in text and "psf_profile" not in text
    with pytest.raises(FileExistsError, match="never overwrites"):
        write_matrix_cell(out, "none", size=(48, 32), pairs=6)
    assert not list(tmp_path.glob(".*tmp*"))


def test_the_same_seed_writes_the_same_dataset_and_another_seed_another(tmp_path: Path) -> None:
    kw = dict(size=(48, 32), pairs=6)
    a, b, c = (write_matrix_cell(tmp_path / n, "misregistration", seed=s, **kw) for n, s in (("a", 1), ("b", 1), ("c", 2)))
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    left = lambda root: cv2.imread(str(next(root.glob("pairs/*/left.png"))), cv2.IMREAD_UNCHANGED)  # noqa: E731
    assert not np.array_equal(left(a), left(c))


def test_sharp_is_the_f22_frame_and_in_focus_the_views_add_up_to_it() -> None:
    """``sharp`` is the whole aperture at its f-number: in focus it equals a pinhole image and L + R; out of focus
    it carries its own disc (second moment c^2 / 16, checked at f/8 where the disc is 1.4 px)."""
    scene = point_scene(SIZE, 24, (47.0, 31.0), 1000.0, sigma_px=1.5)
    s22 = render_sharp(scene, LENS, Effects.of("none"), 22.0, np.random.default_rng(0))
    s0 = render_sharp(scene, LENS, Effects.of("none"), 0.0, np.random.default_rng(0))
    left, right = render_views(scene, LENS, Effects.of("none"), np.random.default_rng(0), samples=SAMPLES)
    np.testing.assert_allclose(s22, s0, atol=1e-5)
    np.testing.assert_allclose(left + right, s22, atol=1e-5)
    blurred = point_scene(SIZE, 24, (47.0, 31.0), 2500.0, sigma_px=1.5)
    s8 = render_sharp(blurred, LENS, Effects.of("none"), 8.0, np.random.default_rng(0), n_half=64)
    c8 = float(Lens(35.0, 8.0, 1000.0, PITCH).coc_px(np.float64(2500.0)))
    assert moments(s8)[3] - moments(s0)[3] == pytest.approx(c8**2 / 16 + INTERPOLATION_VARIANCE_PX2, rel=0.05)
    assert moments(s8)[4] == pytest.approx(moments(s0)[4], rel=1e-5)


def test_the_renderer_shares_no_code_with_dp5k() -> None:
    """Its modules import only the standard library, numpy, OpenCV, tifffile and each other (not dp5k, not
    foreign_dp): an independent implementation of the physics."""
    import ast

    import dp5k_testing.aperture_dp as ap

    allowed = {"json", "math", "os", "shutil", "string", "dataclasses", "pathlib", "typing", "__future__", "cv2", "numpy", "tifffile"}
    for path in (Path(ap.__file__), Path(ap.__file__).with_name("aperture_scene.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                assert {a.name.split(".")[0] for a in node.names} <= allowed, (path.name, ast.dump(node))
            elif isinstance(node, ast.ImportFrom):
                ok = node.module.split(".")[0] in allowed if node.level == 0 else node.module == "aperture_scene"
                assert ok, (path.name, node.module)
