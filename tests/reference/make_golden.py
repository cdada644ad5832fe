"""Write the golden outputs of the equivalence tests whose reference is needed only for its outputs.

Run from the repository root, only when an output is meant to change (a deliberate change of the algorithm or of
the simulated session the inputs come from), and commit the new file with the change that explains it::

    .venv/bin/python -m tests.reference.make_golden

``tests/process/golden/depth_for_camera.npz``: the whole depth step of both cameras of a small simulated wall
session (``dp5k_testing.sim_session.write_session(..., "wall", f_numbers=(1.8,), board_on_wall=True)``), cam0 and
cam1 in turn sharing their code views as ``process_scene`` does: each camera's depth (float32, metres, NaN where
invalid, on its raw pixel grid) and its ``info`` dict (JSON). First written from the depth step as it was before
issue 22's third pass (commit a50fa0b), which the faster code matched bit for bit; ``test_reference_equivalence``
compares the package's ``depth_for_camera`` with it, bit for bit.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

GOLDEN = Path(__file__).resolve().parents[1] / "process" / "golden"
DEPTH_FOR_CAMERA = GOLDEN / "depth_for_camera.npz"


def depth_step_outputs(raw_root: Path) -> dict[str, tuple[np.ndarray, dict[str, Any]]]:
    """Camera -> (depth, info) of ``depth_for_camera`` on the wall session written under ``raw_root``."""
    from dp5k_process.pipeline import ProcessConfig, depth_for_camera
    from dp5k_process.session import load_session
    from dp5k_testing.sim_session import write_session

    from ..process.scene_steps import calibrated_and_decoded

    write_session(raw_root, "wall", f_numbers=(1.8,), board_on_wall=True)
    cfg = ProcessConfig()
    st, decs = calibrated_and_decoded(load_session(raw_root / "wall"), cfg)
    cache: dict = {}
    return {cam: depth_for_camera(decs, cam, st, cfg, cache) for cam in ("cam0", "cam1")}


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        outputs = depth_step_outputs(Path(tmp))
    GOLDEN.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(DEPTH_FOR_CAMERA, **{f"{cam}_depth": d for cam, (d, _) in outputs.items()},
                        **{f"{cam}_info": np.array(json.dumps(info, sort_keys=True)) for cam, (_, info) in outputs.items()})
    print(f"wrote {DEPTH_FOR_CAMERA} ({DEPTH_FOR_CAMERA.stat().st_size / 1024:.0f} KiB)")


if __name__ == "__main__":
    main()
