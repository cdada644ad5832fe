"""``dp5k process`` and ``dp5k validate-depth``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from dp5k_common.cli_conventions import check_out_location, out_option, overwrite_option, refuse_earlier_run, resume_option
from dp5k_common.errors import BadInputError

from .filters import FilterConfig
from .pipeline import ProcessConfig


def _size(text: str | None, what: str) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise BadInputError(f"{what} must look like WxH (e.g. 1680x1120), got {text!r}") from exc
    if w <= 0 or h <= 0:
        raise BadInputError(f"{what} must be positive, got {text!r}")
    return w, h


@click.command("process")
@click.argument("raw", type=click.Path(path_type=Path))
@out_option("The processed dataset (format v1) to write or continue.", legacy_positional=True, resumes=True)
@click.option("--workers", "-j", type=click.IntRange(min=1), default=1, show_default=True,
              help="Scenes processed in parallel (a process pool). Under torchrun --nproc_per_node N each rank "
                   "processes every N-th scene, with its own pool.")
@click.option("--size", "size", default=None, help="Output size WxH (default: half the raw size, 1680x1120 on the 5D IV half-size).")
@click.option("--focus-window", default="30x20", show_default=True,
              help="Eq. 5 window WxH at 1680 px width (scaled with the output; the released code uses 60x40).")
@click.option("--intrinsics", type=click.Path(path_type=Path), default=None,
              help="FileStorage YAML with K0/dist0/K1/dist1 at raw resolution (prior per-camera calibration).")
@click.option("--fill-steps", type=click.IntRange(1, 4), default=3, show_default=True,
              help="Steps of Eq. 3 (3 = scales 1, 1/2, 1/4 as in the paper; 4 adds 1/8). A camera too coarse to "
                   "resolve a scale's projector pixels gets one more (coarser) step per such scale, up to 1/8.")
@click.option("--max-rms", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True, help="Reject a calibration above this reprojection error (px).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Seed of the scene split.")
@resume_option("Skip the scenes OUT already holds (their checksums verified) and process the rest; --no-resume "
               "refuses an OUT that holds processed scenes.")
@overwrite_option("Process every scene again, replacing what OUT holds (e.g. after changing --size); the raw "
                  "sessions are only read.")
def process_command(raw: Path, out: Path, workers: int, size: str | None, focus_window: str, intrinsics: Path | None,
                    fill_steps: int, max_rms: float, seed: int, resume: bool, overwrite: bool) -> None:
    """Process raw capture sessions RAW/<scene>/ into the processed dataset format v1 in --out OUT.

    Calibrates each focus setting from its three ChArUco pairs, decodes the Gray code at projector scales
    1 .. 1/8, triangulates and filters depth per DP camera, estimates the focus distance (Eq. 5), writes
    sharp/left/right/depth/CoC pairs and a report per scene. Finished scenes are skipped (checksums verified);
    a failing scene is reported and skipped, and the command exits with code 8 at the end.

    Under ``torchrun --nproc_per_node N -m dp5k_cli process RAW --out OUT`` the scenes are split over the N ranks
    (RANK / WORLD_SIZE): each scene is written by one rank, each rank resumes its own share.
    """
    from calib.calibrate import CalibConfig

    from .package import process_sessions

    fw = _size(focus_window, "--focus-window")
    assert fw is not None
    cfg = ProcessConfig(out_size=_size(size, "--size"), focus_window_px=fw,
                        intrinsics=None if intrinsics is None else str(intrinsics),
                        filt=dataclasses.replace(FilterConfig(), fill_steps=fill_steps),
                        calib=CalibConfig(max_rms_px=max_rms))
    if not (resume or overwrite):
        refuse_earlier_run(out / "reports", "an earlier run's processed scenes")
    try:
        outcomes = process_sessions(raw, out, cfg, workers=workers, seed=seed, overwrite=overwrite)
    finally:
        echo_warnings(raw, out)
    from dp5k_common.sharding import rank_info

    ok = [o.scene for o in outcomes if o.status == "ok"]
    skipped = sum(o.status == "skipped" for o in outcomes)
    info = rank_info()
    who = f"rank {info.rank} of {info.world_size}: " if info.enabled else ""
    click.echo(f"{who}processed {len(ok)} scene(s){' (' + ', '.join(ok) + ')' if ok else ''}, skipped {skipped} "
               f"finished one(s); dataset in {out}")


def echo_warnings(raw: Path, out: Path) -> None:
    """Repeat, at the end and on stderr, the warnings of the finished scenes of this rank's share (the calibration checks of
    ``dp5k_process.refine``), so that a collapsed or corrected calibration is not lost among the progress lines."""
    from dp5k_common.errors import DP5KError
    from dp5k_common.io import read_json
    from dp5k_common.sharding import rank_info, shard

    from .package import find_sessions

    try:
        scenes = [p.name for p in shard(find_sessions(raw), rank_info())]
    except DP5KError:
        return
    for scene in scenes:
        rp = out / "reports" / scene / "report.json"
        try:
            rep = read_json(rp) if rp.is_file() else {}
        except DP5KError:
            continue
        if rep.get("status") == "ok":
            for w in rep.get("warnings", []):
                click.echo(f"WARNING: scene {scene}: {w}", err=True)


@click.command("validate-depth")
@click.argument("capture", type=click.Path(path_type=Path))
@out_option("Folder for the report and residual picture, replaced on each run.", required=False,
            default_text="CAPTURE/validate-depth")
@click.option("--camera", type=click.Choice(["cam0", "cam1"]), default="cam0", show_default=True)
@click.option("--intrinsics", type=click.Path(path_type=Path), default=None,
              help="FileStorage YAML with K0/dist0/K1/dist1 at raw resolution.")
def validate_depth_command(capture: Path, out: Path | None, camera: str, intrinsics: Path | None) -> None:
    """Depth accuracy on a wall (Eq. 4): a ChArUco board on a wall about 2.2 m away, captured as a session.

    The wall plane comes from the detected board (PnP), independently of the structured light; the error is
    mean point-to-plane distance / mean depth over the structured-light points on the board.
    """
    from .validate import validate_depth

    cfg = ProcessConfig(intrinsics=None if intrinsics is None else str(intrinsics))
    out = out or Path(capture) / "validate-depth"
    check_out_location(out)  # the derived default too (an explicit --out was checked already)
    res = validate_depth(capture, out, cfg, camera=camera)
    click.echo(f"relative error (Eq. 4): {100 * res['relative_error']:.3f} % over {res['n_points']} points at "
               f"{res['mean_depth_m']:.3f} m mean depth (paper: 0.59 %, RealSense D415: 2 %)")
