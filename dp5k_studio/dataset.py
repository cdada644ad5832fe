"""The direct route to learning data: "measured" DP pairs in dataset format v1, with planted effects.

Two sources, one renderer (dp_optics.render_dp, the same optics as ``Studio.expose``):

* :func:`pair_from_rgbd`: any RGBD input (sharp image + depth + imaging parameters) -> sharp / left / right /
  depth / CoC arrays;
* :func:`make_dataset`: studio scenes (random seeds or presets) x cameras x f-numbers -> a dataset folder; or,
  with :class:`RandomCaptures`, scenes x cameras x captures of random focus, f-number, sensor format and gain
  (training data that transfers, issue 33).

Output conventions (docs/data-format.md): ``sharp`` is the f/22 frame of the same lens on the same linear
scale (diffraction included, noise free); ``left + right`` ~ the full-aperture blur of ``sharp`` (Eq. 2);
``coc.tif`` is Eq. 6 with the RECORDED focus distance (``focus_offset`` makes the lens focus elsewhere);
views carry nominal noise ``sigma^2 = NOISE_SHOT * I + NOISE_READ^2`` (linear units) that the ``noise``
effect raises. Each pair's params.json has extra keys ``"effects"`` (planted effects and their physical
parameters; ground truth for tests, never to be read by diagnose to decide), ``"true_focus_distance_mm"``,
``"source"`` and ``"noise"``; dataset.json carries ``"effects"`` and ``"generator"``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from dp5k_common.dataset import PAIR_FILES, PairParams, split_scenes, write_index, write_pair
from dp5k_common.errors import BadInputError
from dp5k_common.optics import coc_diameter_px
from dp5k_common.progress import progress
from dp5k_common.run_progress import RunProgress
from dp5k_common.sensor_noise import NOMINAL_READ_SIGMA, NOMINAL_SHOT_VAR, NoiseModel

from .dp_optics import LensSetting, render_dp
from .effects import EffectSet, effect_parameters, parse_effects
from .render import view_geometry
from .rig import FOCAL_LENGTH_MM, SENSOR_SIZE_MM, make_rig
from .scenes import make_scene

PAPER_F_NUMBERS: tuple[float, ...] = (1.8, 2.0, 2.8, 4.0, 5.6)
CAPTURE_STREAM = 0x63617074
"""Second word of the seed of :class:`RandomCaptures`' draws (a stream apart from the noise's)."""
SHARP_F_NUMBER = 22.0
NOISE_SHOT = NOMINAL_SHOT_VAR
"""Nominal shot-noise variance per unit linear intensity (a ~50 000 e- full well scaled to [0, 1]; the project's
nominal sensor, ``dp5k_common.sensor_noise``)."""
NOISE_READ = NOMINAL_READ_SIGMA
"""Nominal read-noise sigma in linear units."""


def as_effects(effects: EffectSet | Mapping[str, float] | Iterable[str] | None) -> EffectSet:
    """EffectSet from an EffectSet, a {name: strength} mapping, or ``["name=strength", ...]``."""
    if effects is None:
        return EffectSet()
    if isinstance(effects, EffectSet):
        return effects
    if isinstance(effects, Mapping):
        return EffectSet(dict(effects))
    if isinstance(effects, str):
        return parse_effects([effects])
    return parse_effects(list(effects))


def _diffraction(img: NDArray[np.float32], f_number: float, pitch_mm: float) -> NDArray[np.float32]:
    sig = 0.42 * 0.00055 * f_number / pitch_mm
    if sig <= 0.05:
        return img
    return cv2.GaussianBlur(img, (0, 0), sig, borderType=cv2.BORDER_REFLECT)


def view_noise(effects: EffectSet, gain: float = 1.0) -> NoiseModel:
    """The views' sensor noise: nominal, raised by the ``noise`` effect, at ``gain`` x the variance (ISO)."""
    nz = effect_parameters("noise", effects.s("noise"))
    model = NoiseModel.uniform(NOISE_SHOT * nz["shot_var_factor"], NOISE_READ * nz["read_sigma_factor"])
    return model if gain == 1.0 else model.scaled(gain)


@dataclass
class RenderedPair:
    """Arrays of one pair (dataset units): sharp/left/right (H, W, 3) float32 linear in [0, 1],
    depth_mm (H, W) float32 (0 = invalid), coc_px (H, W) float32 (Eq. 6 with the recorded focus),
    extra: params.json extra keys."""

    sharp: NDArray[np.float32]
    left: NDArray[np.float32]
    right: NDArray[np.float32]
    depth_mm: NDArray[np.float32]
    coc_px: NDArray[np.float32]
    extra: dict[str, Any]


def pair_from_rgbd(
    sharp: NDArray[np.floating],
    depth_mm: NDArray[np.floating],
    *,
    f_number: float,
    focus_distance_mm: float,
    focal_length_mm: float = FOCAL_LENGTH_MM,
    pixel_pitch_mm: float | None = None,
    effects: EffectSet | Mapping[str, float] | Iterable[str] | None = None,
    rng: np.random.Generator | None = None,
    noise: bool = True,
    sharp_is_pinhole: bool = False,
    hidden: tuple[NDArray[np.floating], NDArray[np.floating]] | None = None,
    noise_gain: float = 1.0,
) -> RenderedPair:
    """Render "measured" DP views from an RGBD frame.

    Args:
        sharp: (H, W, 3) linear image in [0, 1] (treated as the scene's pinhole radiance).
        depth_mm: (H, W) z-depth in mm, 0 / NaN = invalid (rendered in focus).
        f_number: DP capture f-number.
        focus_distance_mm: the RECORDED focus distance (mm); the lens truly focuses there unless the
            ``focus_offset`` effect is planted.
        focal_length_mm: thin-lens focal length (mm).
        pixel_pitch_mm: of this image; default 36 mm / width (full-frame sensor).
        effects: planted effects.
        rng: noise generator (default seed 0).
        noise: add the nominal (and effect) noise to left/right.
        sharp_is_pinhole: if True, output ``sharp`` is rendered at f/22 from the input; else the input is
            kept as the sharp image.
        hidden: optional ``(radiance, depth_mm)`` of the surfaces behind the visible ones (studio scenes
            know them), for exact partial occlusion at depth edges.
        noise_gain: the views' noise variance times this (a sensor gain, ISO; :func:`view_noise`).

    Returns:
        :class:`RenderedPair`.
    """
    img = np.asarray(sharp, dtype=np.float32)
    if img.ndim != 3 or img.shape[2] != 3:
        raise BadInputError(f"sharp image must be (H, W, 3), got {img.shape}")
    H, W = img.shape[:2]
    z = np.asarray(depth_mm, dtype=np.float64)
    if z.shape != (H, W):
        raise BadInputError(f"depth shape {z.shape} differs from the image's {(H, W)}")
    eff = as_effects(effects)
    rng = rng or np.random.default_rng(0)
    pitch = float(pixel_pitch_mm) if pixel_pitch_mm else SENSOR_SIZE_MM[0] / W
    F_true = float(focus_distance_mm) * effect_parameters("focus_offset", eff.s("focus_offset"))["focus_factor"]
    lens = LensSetting(float(focal_length_mm), float(f_number), F_true, pitch)
    dp = render_dp(img, z, lens, eff, hidden=hidden)
    left = _diffraction(dp.left, f_number, pitch)
    right = _diffraction(dp.right, f_number, pitch)
    if sharp_is_pinhole:
        sh = render_dp(img, z, LensSetting(float(focal_length_mm), SHARP_F_NUMBER, F_true, pitch), EffectSet(), full=True,
                       view_effects=False, hidden=hidden).full
        sharp_out = _diffraction(sh, SHARP_F_NUMBER, pitch)
    else:
        sharp_out = img
    nz = view_noise(eff, noise_gain)
    if noise:
        left = nz.sample(left, rng)
        right = nz.sample(right, rng)
    valid = np.isfinite(z) & (z > 0)
    depth_out = np.where(valid, np.clip(np.rint(z), 0, 65535), 0.0).astype(np.float32)  # depth.png holds whole mm
    valid &= depth_out > 0
    coc = coc_diameter_px(depth_out, float(focus_distance_mm), float(focal_length_mm), float(f_number), pitch)
    extra = {
        "effects": eff.to_json((W, H)),
        "true_focus_distance_mm": F_true,
        "sharp_f_number": SHARP_F_NUMBER if sharp_is_pinhole else 0.0,  # 0: sharp is the input radiance
        "noise": {"shot_var": nz.shot_var[0], "read_sigma": nz.read_sigma[0]} if noise else None,
    }
    return RenderedPair(np.clip(sharp_out, 0, 1).astype(np.float32), np.clip(left, 0, 1), np.clip(right, 0, 1),
                        depth_out, np.where(valid, coc, np.nan).astype(np.float32), extra)


REFERENCE_F_NUMBER = 1.8
"""The f-number at which :class:`RandomCaptures` states a capture's blur range (the widest of the paper's)."""


@dataclass(frozen=True)
class RandomCaptures:
    """Captures drawn at random, for training data that transfers to cameras and renderers not seen (issue 33).

    Per scene and camera, ``per_view`` captures, each its own:

    * **focus**: on the surface under a random point of the frame's central 80 % (the point is ``focus_point_px``);
    * **f-number**: drawn from ``make_dataset``'s ``f_numbers`` (the paper's 1.8-5.6 by default);
    * **sensor format**: the pixel pitch that puts the 99th percentile of |CoC| at f/1.8 at a log-uniform draw from
      ``coc_px`` (px). At a fixed field of view and f-number, a sensor ``s`` x as large blurs ``s`` x as many pixels,
      so this is the format of the camera (a phone's to a full frame's; the paper's Sec. 5.3.1 adjustment, drawn);
      None keeps the rig's full-frame sensor;
    * **sensor gain**: the views' noise variance (:func:`view_noise`) times a log-uniform draw from ``noise_gain``
      (an ISO that many times higher: shot variance x gain, read sigma x sqrt(gain)).

    The default ranges are for frames about 100 px wide: at 96 x 64 the studio's own full-frame 85 mm lens blurs the
    99th percentile by 2.5-37 px at f/1.8 (median 16) with a random focus, which a deblurrer learns as "everything
    is far out of focus" (docs/deblur.md). The format range reaches down to 0.2 px so that some captures are nearly
    all in focus (a small sensor, a far scene, f/5.6): without them a deblurrer never learns to leave sharp content
    alone, and loses many dB on such pairs of another renderer (docs/deblur.md, issue 33).
    """

    per_view: int = 1
    coc_px: tuple[float, float] | None = (0.2, 12.0)
    noise_gain: tuple[float, float] = (1.0, 30.0)

    def __post_init__(self) -> None:
        if self.per_view < 1:
            raise BadInputError(f"need at least one capture per view, got {self.per_view}")
        for name, rng in (("coc_px", self.coc_px), ("noise_gain", self.noise_gain)):
            if rng is not None and not (0 < rng[0] <= rng[1] and math.isfinite(rng[1])):
                raise BadInputError(f"{name} must be a range 0 < low <= high, got {rng[0]}:{rng[1]}")

    def draw(self, rng: np.random.Generator, depth_mm: NDArray[np.floating], f_numbers: Sequence[float],
             focal_length_mm: float) -> tuple[tuple[float, float], float, float, float, float]:
        """One capture of a view with z-depth ``depth_mm`` (H, W; inf / NaN = nothing hit) through a lens of
        ``focal_length_mm``: ((x, y) focus point px, focus distance mm, f-number, pixel pitch mm, noise gain)."""
        H, W = depth_mm.shape
        finite = np.isfinite(depth_mm) & (depth_mm > 1.5 * focal_length_mm)
        x, y = W / 2, H / 2
        focus = float(np.median(depth_mm[finite]))
        for _ in range(50):
            px, py = int(rng.integers(W // 10, W - W // 10)), int(rng.integers(H // 10, H - H // 10))
            if finite[py, px]:
                x, y, focus = float(px), float(py), float(depth_mm[py, px])
                break
        n = float(f_numbers[int(rng.integers(len(f_numbers)))])
        pitch = SENSOR_SIZE_MM[0] / W
        if self.coc_px is not None:
            c_mm = np.abs(coc_diameter_px(depth_mm[finite], focus, focal_length_mm, REFERENCE_F_NUMBER, 1.0))  # on the sensor
            p99 = float(np.percentile(c_mm, 99))
            if p99 > 0:
                pitch = p99 / math.exp(rng.uniform(*np.log(self.coc_px)))
        gain = math.exp(rng.uniform(*np.log(self.noise_gain)))
        return (x, y), focus, n, pitch, gain


PROGRESS_FILE = ".make-dataset-progress.json"
"""In OUT while a dataset is being written: the options and how far it got (:class:`~dp5k_common.run_progress.RunProgress`);
a rerun with the same options continues from it, and the finished dataset is the one an uninterrupted run writes."""


def _start(out: Path, settings: dict[str, Any], overwrite: bool) -> tuple[RunProgress, dict[str, Any] | None]:
    """The progress file of a make-dataset run into ``out`` and the state of an interrupted run to continue (None:
    start afresh).

    Raises:
        BadInputError: ``out`` holds a finished dataset, an interrupted run with other options, or pairs that no
            make-dataset run here left (each unless ``overwrite``), or an interrupted run's pair is gone.
    """
    prog = RunProgress(out / PROGRESS_FILE, settings)
    if overwrite:
        prog.finish()
        return prog, None
    if (out / "dataset.json").exists():
        raise BadInputError("dataset already exists; add --overwrite to replace it, or choose another --out",
                            where=out / "dataset.json")
    other = prog.other_settings()
    if other is not None:
        raise BadInputError(f"an interrupted make-dataset with other options is here ({prog.differences(other)}); run it "
                            "again with its options to finish it, add --overwrite to start afresh, or choose another --out",
                            where=out)
    state = prog.earlier()
    if state is None:
        if (out / "pairs").is_dir() and any((out / "pairs").iterdir()):
            raise BadInputError("holds pairs but neither a dataset nor an interrupted make-dataset; add --overwrite to "
                                "replace them, or choose another --out", where=out / "pairs")
        return prog, None
    for pids in state["scene_ids"].values():
        for pid in pids:
            if not all((out / "pairs" / pid / name).is_file() for name in PAIR_FILES):
                raise BadInputError("an interrupted make-dataset is here but its pair is gone or incomplete; add "
                                    "--overwrite to start afresh", where=out / "pairs" / pid)
    return prog, state


def _scene_list(scenes: int | Sequence[str | int], seed: int) -> list[str | int]:
    if isinstance(scenes, (int, np.integer)):
        if scenes < 1:
            raise BadInputError(f"need at least one scene, got {scenes}")
        return [int(seed) * 100003 + k for k in range(int(scenes))]
    return list(scenes)


def make_dataset(
    out_dir: str | os.PathLike[str],
    scenes: int | Sequence[str | int] = 3,
    effects: EffectSet | Mapping[str, float] | Iterable[str] | None = None,
    size: tuple[int, int] = (288, 192),
    f_numbers: Sequence[float] = PAPER_F_NUMBERS,
    cameras: Sequence[int] = (0, 1),
    seed: int = 0,
    supersample: int = 2,
    overwrite: bool = False,
    noise: bool = True,
    all_in_focus_sharp: bool = False,
    random_captures: RandomCaptures | None = None,
) -> Path:
    """Write a format-v1 dataset of studio scenes with planted effects.

    Args:
        out_dir: dataset folder (created). A finished dataset there is refused unless ``overwrite``; an interrupted
            run with the same arguments is continued (its pairs kept, :data:`PROGRESS_FILE`).
        scenes: a number of random scenes (seeds derived from ``seed``) or a list of presets / seeds.
        effects: planted effects (EffectSet, {name: strength} or ["name=strength"]).
        size: output (W, H) in px; the pixel pitch is 36 mm / W.
        f_numbers: DP f-numbers per scene and camera (a pair each).
        cameras: camera indices (0, 1).
        seed: master seed (scenes, noise).
        supersample: rays per pixel side.
        overwrite: replace existing pairs.
        noise: add nominal noise to the DP views.
        all_in_focus_sharp: write the rendered radiance as ``sharp`` (``sharp_f_number`` 0) instead of the
            f/22 capture, as a generator that blurs ``sharp`` itself would.
        random_captures: instead of every f-number at the scene's own focus with the rig's sensor, draw this many
            captures per scene and camera, each with its own focus, f-number (from ``f_numbers``), sensor format
            and gain (:class:`RandomCaptures`); pair ids ``<scene>_<camera>_c<k>``, and params.json's extra
            ``capture`` holds the draws.

    Returns:
        The dataset folder. Pair ids are ``<scene>_<camera>_f<N>``; splits are by scene.
    """
    eff = as_effects(effects)
    W, H = int(size[0]), int(size[1])
    if W < 16 or H < 16:
        raise BadInputError(f"image size must be at least 16 x 16, got {W} x {H}")
    out = Path(out_dir)
    items = _scene_list(scenes, seed)
    settings = {"scenes": items, "effects": eff.to_json((W, H)), "size": [W, H], "f_numbers": [float(n) for n in f_numbers],
                "cameras": [int(c) for c in cameras], "seed": int(seed), "supersample": int(supersample),
                "noise": bool(noise), "all_in_focus_sharp": bool(all_in_focus_sharp),
                "random_captures": asdict(random_captures) if random_captures is not None else None}
    prog, earlier = _start(out, settings, overwrite)
    rig = make_rig(6720.0 / W)
    rng = np.random.default_rng(seed)
    draws = np.random.default_rng([int(seed), CAPTURE_STREAM])  # apart from the noise: the same captures with or without it
    scene_ids: dict[str, list[str]] = {}
    jobs = [(sc, cam) for sc in items for cam in cameras]
    done = 0
    if earlier is not None:  # continue: the generators where the last finished view left them
        done, scene_ids = int(earlier["done"]), earlier["scene_ids"]
        rng.bit_generator.state, draws.bit_generator.state = earlier["rng"], earlier["draws"]
        overwrite = True  # the view that was interrupted may have written some of its pairs
    else:
        prog.save({"done": 0, "scene_ids": {}, "rng": rng.bit_generator.state, "draws": draws.bit_generator.state})
    for j, (sc, cam_i) in enumerate(progress(jobs[done:], desc="studio pairs", unit="view"), start=done):
        scene = make_scene(sc, rig)
        cam = rig.cameras[cam_i].scaled(W, H)
        geom = view_geometry(scene, cam, None, (), supersample)
        radiance = geom.radiance(None)
        depth_mm = geom.depth_m * 1000.0
        hidden = (geom.hidden_radiance(None), geom.hidden["depth_m"] * 1000.0) if geom.hidden is not None else None
        if random_captures is not None:
            for k in range(random_captures.per_view):
                point, focus, n, pitch, gain = random_captures.draw(draws, depth_mm, f_numbers, cam.focal_length_mm)
                rp = pair_from_rgbd(radiance, depth_mm, f_number=n, focus_distance_mm=focus,
                                    focal_length_mm=cam.focal_length_mm, pixel_pitch_mm=pitch, effects=eff, rng=rng,
                                    noise=noise, sharp_is_pinhole=not all_in_focus_sharp, hidden=hidden, noise_gain=gain)
                pair_id = f"{scene.name}_{cam.name}_c{k}"
                params = PairParams(pair_id, scene.name, cam.name, n, focus, cam.focal_length_mm, pitch, point, (W, H),
                                    {**rp.extra, "source": "studio", "scene_seed": scene.seed,
                                     "capture": {"noise_gain": gain, "sensor_scale": SENSOR_SIZE_MM[0] / W / pitch}})
                write_pair(out, params, sharp=rp.sharp, left=rp.left, right=rp.right, depth_mm=rp.depth_mm,
                           coc_px=rp.coc_px, overwrite=overwrite, sub_mm_depth=True)
                scene_ids.setdefault(scene.name, []).append(pair_id)
            prog.save({"done": j + 1, "scene_ids": scene_ids, "rng": rng.bit_generator.state,
                       "draws": draws.bit_generator.state})
            continue
        Xc = cam.R @ scene.focus_target_m + cam.t
        uv = cam.K @ (Xc / Xc[2])
        fx = float(np.clip(np.rint(uv[0]), 0, W - 1))
        fy = float(np.clip(np.rint(uv[1]), 0, H - 1))
        F_rec = float(depth_mm[int(fy), int(fx)])
        if not np.isfinite(F_rec) or F_rec <= cam.focal_length_mm * 1.5:
            F_rec = float(np.median(depth_mm[np.isfinite(depth_mm)]))
        sharp = None
        for N in f_numbers:
            rp = pair_from_rgbd(radiance, depth_mm, f_number=float(N), focus_distance_mm=F_rec,
                                focal_length_mm=cam.focal_length_mm, pixel_pitch_mm=cam.pixel_pitch_mm,
                                effects=eff, rng=rng, noise=noise, sharp_is_pinhole=sharp is None and not all_in_focus_sharp,
                                hidden=hidden)
            if sharp is None:
                sharp = rp.sharp
            pair_id = f"{scene.name}_{cam.name}_f{N:g}"
            params = PairParams(pair_id, scene.name, cam.name, float(N), F_rec, cam.focal_length_mm, cam.pixel_pitch_mm,
                                (fx, fy), (W, H), {**rp.extra, "sharp_f_number": 0.0 if all_in_focus_sharp else SHARP_F_NUMBER,  # pairs share the first render
                                                   "source": "studio", "scene_seed": scene.seed})
            write_pair(out, params, sharp=sharp, left=rp.left, right=rp.right, depth_mm=rp.depth_mm, coc_px=rp.coc_px,
                       overwrite=overwrite, sub_mm_depth=True)
            scene_ids.setdefault(scene.name, []).append(pair_id)
        prog.save({"done": j + 1, "scene_ids": scene_ids, "rng": rng.bit_generator.state, "draws": draws.bit_generator.state})
    split = split_scenes(list(scene_ids), seed=seed)
    splits = {name: [pid for sc in scs for pid in scene_ids[sc]] for name, scs in split.items()}
    write_index(out, splits, effects=eff.to_json((W, H)),
                generator={"tool": "dp5k studio make-dataset", "seed": int(seed), "size": [W, H],
                           "f_numbers": [float(n) for n in f_numbers], "scenes": [str(s) for s in items],
                           **({"random_captures": asdict(random_captures)} if random_captures is not None else {})})
    prog.finish()
    return out


def make_dataset_from_rgbd(
    out_dir: str | os.PathLike[str],
    source: str | os.PathLike[str],
    effects: EffectSet | Mapping[str, float] | Iterable[str] | None = None,
    seed: int = 0,
    overwrite: bool = False,
    noise: bool = True,
) -> Path:
    """Re-render the DP views of every pair of an existing format-v1 dataset (any RGBD source: processed
    captures, imported RGBD frames) with planted effects; sharp, depth, parameters and splits are kept.

    Each source pair's ``sharp`` is treated as the pinhole radiance, its ``depth.png`` as z-depth (0 =
    invalid, rendered in focus) and its params (f-number, recorded focus distance, focal length, pixel
    pitch) as the capture settings.

    Returns:
        The new dataset folder.
    """
    from dp5k_common.dataset import DatasetReader

    eff = as_effects(effects)
    src = DatasetReader(source)
    out = Path(out_dir)
    if out.resolve() == Path(source).resolve():
        raise BadInputError("output must differ from the source dataset", where=out)
    settings = {"source": str(Path(source).resolve()), "effects": eff.to_json(), "seed": int(seed), "noise": bool(noise)}
    prog, earlier = _start(out, settings, overwrite)
    rng = np.random.default_rng(seed)
    ids, done = src.ids(), 0
    if earlier is not None:
        done = int(earlier["done"])
        rng.bit_generator.state = earlier["rng"]
        overwrite = True
    else:
        prog.save({"done": 0, "scene_ids": {}, "rng": rng.bit_generator.state})
    for j, pid in enumerate(progress(ids[done:], desc="re-render pairs", unit="pair"), start=done):
        pair = src.load(pid)
        pp = pair.params
        rp = pair_from_rgbd(pair.sharp, np.where(pair.valid, pair.depth_mm, 0.0), f_number=pp.f_number,
                            focus_distance_mm=pp.focus_distance_mm, focal_length_mm=pp.focal_length_mm,
                            pixel_pitch_mm=pp.pixel_pitch_mm, effects=eff, rng=rng, noise=noise)
        extra = {k: v for k, v in pp.extra.items() if k not in rp.extra}
        params = PairParams(pp.pair_id, pp.scene, pp.camera, pp.f_number, pp.focus_distance_mm, pp.focal_length_mm,
                            pp.pixel_pitch_mm, pp.focus_point_px, pp.image_size,
                            {**extra, **rp.extra, "source": "rgbd", "source_dataset": str(Path(source).name)})
        write_pair(out, params, sharp=pair.sharp, left=rp.left, right=rp.right, depth_mm=rp.depth_mm,
                   coc_px=rp.coc_px, overwrite=overwrite, sub_mm_depth=True)
        prog.save({"done": j + 1, "scene_ids": {"": ids[:j + 1]}, "rng": rng.bit_generator.state})
    write_index(out, {name: src.ids(name) for name in src.splits}, effects=eff.to_json(),
                generator={"tool": "dp5k studio make-dataset --from", "seed": int(seed), "source": str(source)})
    prog.finish()
    return out
