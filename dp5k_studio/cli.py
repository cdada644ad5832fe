"""``dp5k studio ...``: make learning datasets from the virtual studio, preview scenes, list effects."""

from __future__ import annotations

from pathlib import Path

import click

from dp5k_common.cli_conventions import out_option, overwrite_option
from dp5k_common.errors import BadInputError


def _range(text: str, option: str) -> tuple[float, float]:
    """``LO:HI`` -> (lo, hi) floats (a one-line error naming the option otherwise)."""
    try:
        lo, hi = (float(v) for v in text.split(":"))
    except ValueError as exc:
        raise BadInputError(f"must look like LOW:HIGH, got {text!r}", where=option) from exc
    if not 0 < lo <= hi < float("inf"):
        raise BadInputError(f"must be a range 0 < LOW <= HIGH, got {text!r}", where=option)
    return lo, hi


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise BadInputError(f"--size must look like 288x192, got {text!r}") from exc
    if w < 16 or h < 16:
        raise BadInputError(f"--size must be at least 16x16, got {text!r}", where="--size")
    return w, h


@click.group("studio")
def studio_group() -> None:
    """The virtual studio: scenes with known truth, simulated captures, learning data with planted effects."""


@studio_group.command("make-dataset")
@out_option("The format-v1 dataset to write. An interrupted run continues in it (run the same command again); a "
            "finished dataset is refused unless --overwrite.", legacy_positional=True, resumes=True)
@click.option("--scenes", "n_scenes", type=click.IntRange(min=1), default=3, show_default=True, help="Number of random scenes.")
@click.option("--scene", "scene_names", multiple=True, help="Use these presets / seeds instead (repeatable).")
@click.option("--effect", "effects", multiple=True, help="Plant an effect, NAME=STRENGTH (repeatable; 1.0 = moderate).")
@click.option("--size", default="288x192", show_default=True, help="Output WxH in px.")
@click.option("--f-numbers", default="1.8,2,2.8,4,5.6", show_default=True, help="Comma-separated DP f-numbers.")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--no-noise", is_flag=True, help="Write noise-free DP views.")
@overwrite_option("Replace the pairs of a dataset OUT already holds (or start an interrupted one afresh).")
@click.option("--from", "source", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Re-render the DP views of this format-v1 dataset (any RGBD source) instead of studio scenes.")
@click.option("--camera", "cameras", type=click.IntRange(0, 1), multiple=True,
              help="Render this body only (repeatable; default both).")
@click.option("--all-in-focus-sharp", is_flag=True,
              help="Write the rendered radiance as sharp (sharp_f_number 0) instead of the f/22 capture.")
@click.option("--random-captures", type=click.IntRange(min=1), default=None,
              help="Instead of every f-number at the scene's own focus: this many captures per scene and camera, each "
                   "with a random focus, f-number (from --f-numbers), sensor format and gain (training data that "
                   "transfers, docs/deblur.md).")
@click.option("--coc-px", default="0.2:12", show_default=True,
              help="With --random-captures: the 99th-percentile |CoC| at f/1.8 is drawn log-uniform from LOW:HIGH px "
                   "(the sensor format); 'rig' keeps the rig's full-frame sensor.")
@click.option("--noise-gain", default="1:30", show_default=True,
              help="With --random-captures: the views' noise variance times a log-uniform LOW:HIGH (the sensor gain).")
def make_dataset_command(out: Path, n_scenes: int, scene_names: tuple[str, ...], effects: tuple[str, ...], size: str,
                         f_numbers: str, seed: int, no_noise: bool, overwrite: bool, source: Path | None,
                         cameras: tuple[int, ...], all_in_focus_sharp: bool, random_captures: int | None, coc_px: str,
                         noise_gain: str) -> None:
    """Render a format-v1 dataset (scene x camera x f-number pairs, or x random captures) into --out OUT."""
    from .dataset import RandomCaptures, make_dataset, make_dataset_from_rgbd
    from .effects import parse_effects

    eff = parse_effects(effects)
    captures = None
    if random_captures is not None:
        captures = RandomCaptures(random_captures, None if coc_px == "rig" else _range(coc_px, "--coc-px"),
                                  _range(noise_gain, "--noise-gain"))
    if source is not None:
        path = make_dataset_from_rgbd(out, source, eff, seed=seed, overwrite=overwrite, noise=not no_noise)
        click.echo(f"wrote {path} from {source} ({', '.join(eff.names()) or 'no effects'})")
        return
    try:
        fns = [float(v) for v in f_numbers.split(",") if v.strip()]
    except ValueError as exc:
        raise BadInputError(f"--f-numbers must be comma-separated numbers, got {f_numbers!r}") from exc
    scenes = list(scene_names) if scene_names else n_scenes
    path = make_dataset(out, scenes=scenes, effects=eff, size=_size(size), f_numbers=fns, seed=seed,
                        overwrite=overwrite, noise=not no_noise, cameras=cameras or (0, 1),
                        all_in_focus_sharp=all_in_focus_sharp, random_captures=captures)
    click.echo(f"wrote {path} ({', '.join(eff.names()) or 'no effects'})")


@studio_group.command("render")
@click.argument("scene")
@out_option("The PNG to write (replaced if it exists).", legacy_positional=True, file=True)
@click.option("--scale", default="small", show_default=True, help="Rig scale: small, medium, paper or a factor.")
@click.option("--camera", type=click.IntRange(0, 1), default=0, show_default=True)
@click.option("--f-number", type=click.FloatRange(min=0, min_open=True), default=1.8, show_default=True)
@click.option("--effect", "effects", multiple=True, help="NAME=STRENGTH (repeatable).")
def render_command(scene: str, out: Path, scale: str, camera: int, f_number: float, effects: tuple[str, ...]) -> None:
    """Preview SCENE (preset or seed): writes --out OUT as an sRGB PNG strip: sharp | left | right | depth."""
    import numpy as np

    from dp5k_common.io import atomic_path

    from .effects import parse_effects
    from .rig import make_rig
    from .scenes import make_scene
    from .studio import Studio

    import cv2

    sc: float | str = float(scale) if scale.replace(".", "", 1).isdigit() else scale
    rig = make_rig(sc)
    st = Studio(make_scene(int(scene) if scene.isdigit() else scene, rig), rig, parse_effects(effects))
    fp = st.focus_point_px(camera)
    F = st.focus_distance_m(camera, fp)
    dp = st.render_views(camera, f_number, F)
    sharp = st.radiance(camera)
    depth = st.geometry(camera).depth_m
    d = np.where(np.isfinite(depth), 1.0 - np.clip(np.log(depth / 0.25) / np.log(40.0), 0, 1), 0.0)
    strip = np.concatenate([sharp, 2 * dp.left, 2 * dp.right, np.repeat(d[:, :, None], 3, 2)], axis=1)
    img = (np.clip(strip, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)[:, :, ::-1]
    with atomic_path(out, suffix=".png") as tmp:
        cv2.imwrite(str(tmp), img)
    click.echo(f"wrote {out} (focus {F:.3f} m at {fp})")


@studio_group.command("effects")
def effects_command() -> None:
    """List the plantable effects and what strength 1.0 means."""
    from .effects import __doc__ as table

    click.echo(table)
