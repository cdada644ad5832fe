"""Pairs without valid depth (a DPDD import) are left out of evaluate, named in its report; never NaN metrics."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dp5k_common.dataset import write_index, write_pair
from dp5k_testing.tiny_dataset import make_arrays, make_params
from neural_dp.evaluate import evaluate


def test_pairs_without_depth_are_left_out_and_named(tmp_path: Path) -> None:
    root = tmp_path / "ds"
    splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
    for i, (split, has_depth) in enumerate([("train", True), ("val", True), ("test", True), ("test", False)]):
        params = make_params(f"s{i}_cam0_f1.8", scene=f"s{i}")
        arrays = make_arrays(params, seed=i)
        if not has_depth:
            arrays["depth_mm"] = np.zeros_like(arrays["depth_mm"])
            arrays["coc_px"] = np.full_like(arrays["coc_px"], np.nan)
        write_pair(root, params, **arrays)
        splits[split].append(params.pair_id)
    write_index(root, splits, source="tests")
    res = evaluate(root, tmp_path / "ev", simulators=["disk"], figures=0)
    rep = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert rep["pairs"] == ["s2_cam0_f1.8"] and rep["pairs_without_depth"] == ["s3_cam0_f1.8"]
    assert res.means["disk"]["pairs"] == 1 and np.isfinite(res.means["disk"]["psnr"])
