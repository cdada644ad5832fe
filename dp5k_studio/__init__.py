"""The virtual studio: a world with known truth for every dp5k stage (issue 3).

Scenes of analytic primitives with procedural textures, the paper's rig (two Canon EOS 5D Mark IV + EF
85 mm f/1.8 on a stereo baseline, an EPSON EB-U42 projector), and renderers for structured light,
ChArUco boards, Dual Pixel RAW captures at any f-number and focus, and the f/22 sharp frame, with the
physical DP effects of :data:`dp5k_common.effects.EFFECT_NAMES` plantable at chosen strengths.
The studio never imports the models it is used to judge (neural_dp, dp5k_diagnose).

Units: metres for the world (``_m``), mm on the sensor and for depth in datasets (``_mm``), pixels
(``_px``); OpenCV camera frames, ``X_cam = R X_world + t``.

Usage::

    from dp5k_studio import make_rig, make_scene, Studio, EffectSet
    rig = make_rig("small")                       # raw 336 x 224 per camera
    studio = Studio(make_scene("demo01"), rig, EffectSet.of(disparity_scale=1.0), seed=0)
    x, y = studio.focus_point_px(0)
    F_m = studio.focus_distance_m(0, (x, y))      # true z at the focus point
    raw = studio.expose(0, f_number=1.8, focus_distance_m=F_m, shutter_s=1 / 100, iso=100)
    raw.main, raw.aux                             # (224, 336) uint16 RGGB, main = L + R, aux = L
    truth = studio.ground_truth(0)                # depth_m, K, dist, R, t, proj_xy, ...
    studio.set_projector_image(pattern)           # (1200, 1920) Gray code etc.; None = dark
    studio.set_board_pose((R_board_to_world, t_m))  # calib.board.DEFAULT_BOARD in the scene

    from dp5k_studio import make_dataset
    make_dataset("out/ds", scenes=3, effects=["misregistration=1"], size=(288, 192))

Exports: ``make_rig, Rig, CameraModel, ProjectorModel`` (rig.py); ``make_scene, Scene, PRESETS,
plane_scene, wall_board_pose`` (scenes.py); ``Studio`` (studio.py); ``RawExposure, SensorModel``
(sensor.py); ``EffectSet, parse_effect, parse_effects, effect_parameters`` (effects.py);
``LensSetting, render_dp, plan_dp, DPPlan, left_kernel, coc_channels_px`` (dp_optics.py); ``make_dataset,
make_dataset_from_rgbd, pair_from_rgbd, RenderedPair, RandomCaptures`` (dataset.py).
"""

from .dataset import PAPER_F_NUMBERS, RandomCaptures, RenderedPair, make_dataset, make_dataset_from_rgbd, pair_from_rgbd
from .dp_optics import DPPlan, DPRender, LensSetting, coc_channels_px, left_kernel, plan_dp, render_dp
from .effects import EffectSet, effect_parameters, parse_effect, parse_effects
from .rig import SCALES, CameraModel, ProjectorModel, Rig, make_rig
from .scenes import PRESETS, Scene, make_scene, plane_scene, wall_board_pose
from .sensor import DEFAULT_SENSOR, RawExposure, SensorModel
from .studio import Studio

__all__ = [
    "PAPER_F_NUMBERS", "PRESETS", "SCALES", "DEFAULT_SENSOR",
    "CameraModel", "DPPlan", "DPRender", "EffectSet", "LensSetting", "ProjectorModel", "RandomCaptures", "RawExposure", "RenderedPair", "Rig",
    "Scene", "SensorModel", "Studio",
    "coc_channels_px", "effect_parameters", "left_kernel", "make_dataset", "make_dataset_from_rgbd", "make_rig", "make_scene",
    "pair_from_rgbd", "parse_effect", "parse_effects", "plan_dp", "plane_scene", "render_dp", "wall_board_pose",
]
