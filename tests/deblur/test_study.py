"""``dp5k study downstream`` end to end on a tiny run: both tables, the figure and the settings are written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.errors import BadInputError
from dp5k_deblur.study import few_pairs_dataset
from dp5k_demo.rgbd import write_rgbd_frames
from dp5k_studio import make_dataset
from dp5k_testing.tiny_dataset import make_tiny_dataset

TINY = ["--set", "data.crop_px=32", "--set", "data.samples_per_epoch=16", "--set", "optim.epochs=2",
        "--set", "model.base_channels=4", "--set", "model.levels=2", "--few-real-pairs", "2", "--finetune-epochs", "1"]


@pytest.mark.slow
def test_study_writes_tables_3_and_4(tmp_path: Path) -> None:
    aif = make_dataset(tmp_path / "aif", scenes=4, size=(64, 48), f_numbers=(2.0,), cameras=(0,), seed=11, noise=False,
                       all_in_focus_sharp=True)
    write_rgbd_frames(aif, tmp_path / "rgbd", count=4)
    measured = make_dataset(tmp_path / "measured", scenes=6, size=(64, 48), f_numbers=(2.0,), cameras=(0,), seed=12,
                            effects={"lr_gain_imbalance": 0.5})
    out = tmp_path / "study"
    res = CliRunner().invoke(main, ["-q", "study", "downstream", str(tmp_path / "rgbd"), str(measured), "--out", str(out),
                                    "--simulator", "disk", "--simulator", "base", *TINY])
    assert res.exit_code == 0, res.output
    t3 = json.loads((out / "table3.json").read_text())
    t4 = json.loads((out / "table4.json").read_text())
    test_ids = json.loads((measured / "dataset.json").read_text())["splits"]["test"]
    assert t3["test_pairs"] == t4["test_pairs"] == test_ids and t3["test_data"] == str(measured)
    assert [r.get("simulator") for r in t3["rows"]] == [None, "disk", "base"]
    assert [r.get("simulator") for r in t4["rows"]] == [None, None, "disk", "base"]
    for r in t3["rows"] + t4["rows"]:
        assert 5 < r["psnr"] < 60 and 0 < r["ssim"] <= 1
    # the two simulators' deblurrers differ (their training data did), the floor is the blurred input
    assert t3["rows"][1]["psnr"] != t3["rows"][2]["psnr"]
    assert "Test data: the test split of" in (out / "table3.md").read_text()
    assert (out / "figure.png").stat().st_size > 1000
    study = json.loads((out / "study.json").read_text())
    assert study["config"]["few_real_pairs"] == 2 and set(study["timings_s"]) == {"real", "disk", "base"}
    synth = [json.loads((out / "synth" / s / "dataset.json").read_text()) for s in ("disk", "base")]
    assert synth[0]["splits"] == synth[1]["splits"]  # the same frames


def test_few_pairs_dataset_copies_the_first_train_pairs_and_refuses_another_count(tmp_path: Path) -> None:
    splits = make_tiny_dataset(tmp_path / "real", scenes=6)
    few = few_pairs_dataset(tmp_path / "real", tmp_path / "few", 1)
    index = json.loads((few / "dataset.json").read_text())["splits"]
    assert index == {"train": splits["train"][:1], "val": splits["val"], "test": []}
    assert (few / "pairs" / splits["train"][0] / "params.json").is_file()
    assert few_pairs_dataset(tmp_path / "real", tmp_path / "few", 1) == few  # a resumed study reuses it
    with pytest.raises(BadInputError, match="another set of few measured pairs"):
        few_pairs_dataset(tmp_path / "real", tmp_path / "few", 2)
    with pytest.raises(BadInputError, match="needs 5 train pairs"):
        few_pairs_dataset(tmp_path / "real", tmp_path / "other", 5)
