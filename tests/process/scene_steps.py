"""The first steps of ``process_scene`` for tests that check a later step on a real session's data."""

from __future__ import annotations

from dp5k_process.graycode import GrayCodeConfig, GrayDecode
from dp5k_process.pipeline import ProcessConfig, calibrate_session, decode_camera, read_main
from dp5k_process.session import Session


def calibrated_and_decoded(session: Session, cfg: ProcessConfig):
    """(stereo calibration at the raw size, {camera: Gray-code decode}) as ``process_scene`` computes them."""
    probe = read_main(session, session.cameras["cam0"].sl[-1])[0]
    st, _ = calibrate_session(session, cfg, (probe.shape[1], probe.shape[0]))
    gcfg = cfg.gray or GrayCodeConfig.for_linear_raw(*session.projector_size)
    decs: dict[str, GrayDecode] = {c: decode_camera(session, c, gcfg)[0] for c in ("cam0", "cam1")}
    return st, decs
