"""``dp5k study downstream`` end to end on a tiny run: the Neural DP Simulator trained in the study, two seeds, two
test sets, Tables 3 and 4 with intervals, the differences and which are resolved."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.errors import BadInputError
from dp5k_deblur.study import StudyConfig, few_pairs_dataset
from dp5k_demo.rgbd import write_rgbd_frames
from dp5k_studio import make_dataset
from dp5k_testing.tiny_dataset import make_tiny_dataset

TINY = ["--set", "data.crop_px=32", "--set", "data.samples_per_epoch=16", "--set", "optim.epochs=1",
        "--set", "model.base_channels=4", "--set", "model.levels=2", "--few-real-pairs", "2", "--finetune-epochs", "1",
        "--neural-channels", "4", "--neural-levels", "2", "--seeds", "0,1"]


@pytest.mark.slow
def test_study_with_neural_dp_two_seeds_and_two_test_sets(tmp_path: Path) -> None:
    aif = make_dataset(tmp_path / "aif", scenes=4, size=(64, 48), f_numbers=(2.0,), cameras=(0,), seed=11, noise=False,
                       all_in_focus_sharp=True)
    write_rgbd_frames(aif, tmp_path / "rgbd", count=4)
    measured = make_dataset(tmp_path / "measured", scenes=6, size=(64, 48), f_numbers=(2.0, 4.0), cameras=(0,), seed=12,
                            effects={"lr_gain_imbalance": 0.5})
    real = make_dataset(tmp_path / "real", scenes=5, size=(64, 48), f_numbers=(4.0,), cameras=(0,), seed=13,
                        effects={"disparity_scale": 0.5})
    out = tmp_path / "study"
    res = CliRunner().invoke(main, ["-q", "study", "downstream", str(tmp_path / "rgbd"), str(measured), "--out", str(out),
                                    "--real", str(real), "--simulator", "disk", *TINY])
    assert res.exit_code == 0, res.output
    assert "Test set `real`" in res.output and "Resolved" in res.output
    # the Neural DP Simulator was trained on the measured train split, once per seed, and synthesized with
    for seed in (0, 1):
        assert (out / "neural" / f"seed{seed}" / "best.pt").is_file()
        ckpt = json.loads((out / "neural" / f"seed{seed}" / "config.json").read_text())
        assert ckpt["seed"] == seed and ckpt["model"]["base_channels"] == 4
        synth = json.loads((out / "synth" / f"seed{seed}" / "neural" / "dataset.json").read_text())
        assert f"seed{seed}/best.pt" in json.dumps(synth)
    for test, data in (("measured", measured), ("real", real)):
        t3 = json.loads((out / test / "table3.json").read_text())
        t4 = json.loads((out / test / "table4.json").read_text())
        test_ids = json.loads((data / "dataset.json").read_text())["splits"]["test"]
        assert t3["test_pairs"] == t4["test_pairs"] == test_ids and t3["test_data"] == str(data) and t3["seeds"] == [0, 1]
        assert [r.get("simulator") for r in t3["rows"]] == [None, "disk", "neural"]
        assert [r.get("simulator") for r in t4["rows"]] == [None, None, "disk", "neural"]
        for r in t3["rows"] + t4["rows"]:
            assert 5 < r["psnr"] < 60 and 0 < r["ssim"] <= 1
            for m in ("psnr", "ssim", "mae"):
                lo, hi = r[f"{m}_ci95"]
                assert lo <= r[m] <= hi
        floor, disk = t3["rows"][0], t3["rows"][1]
        assert len(floor["per_seed"]["psnr"]) == 1 and "psnr_gain_vs_input" not in floor  # the input has no seed
        assert len(disk["per_seed"]["psnr"]) == 2 and disk["per_seed"]["psnr"][0] != disk["per_seed"]["psnr"][1]
        gain = disk["psnr_gain_vs_input"]
        assert gain["mean"] == pytest.approx(disk["psnr"] - floor["psnr"], abs=1e-9)
        diffs = json.loads((out / test / "differences.json").read_text())
        for d in diffs["differences"]:
            lo, hi = d["difference"]["ci95"]
            assert d["difference"]["mean"] >= 0 and d["resolved"] == (lo > 0 or hi < 0)
        pairs = {(d["a"], d["b"]) for d in diffs["differences"]}
        assert {("synthetic: disk", "synthetic: neural"), ("synthetic: neural", "synthetic: disk")} & pairs
        assert (out / test / "figure.png").stat().st_size > 1000
    study = json.loads((out / "study.json").read_text())
    assert study["seeds"] == [0, 1] and study["config"]["few_real_pairs"] == 2
    assert set(study["cpu_s"]) >= {"neural: training on the measured train split", "disk: synthesis + deblurrers"}
    assert all(v > 0 for v in study["cpu_s"].values())
    # the synthetic pairs carry dp5k synthesize's default sensor noise (issue 33 section 1), and study.json says so
    assert set(study["synthetic_noise"]) == {"disk", "neural"}
    assert all(m is not None and m["source"] == "nominal" and m["shot_var"][0] > 0 for m in study["synthetic_noise"].values())
    # every seed drew its own optics: the synthetic training sets differ between seeds
    p0 = [json.loads(p.read_text())["f_number"] for p in sorted((out / "synth" / "seed0" / "disk" / "pairs").glob("*/params.json"))]
    p1 = [json.loads(p.read_text())["f_number"] for p in sorted((out / "synth" / "seed1" / "disk" / "pairs").glob("*/params.json"))]
    assert len(p0) == len(p1) == 4 and p0 != p1


def test_two_simulators_under_one_label_are_refused_before_any_work(tmp_path: Path) -> None:
    ckpt = tmp_path / "n.pt"
    ckpt.write_bytes(b"x")
    with pytest.raises(BadInputError, match="one label per simulator"):
        StudyConfig(simulators=(f"neural:{ckpt}",)).specs()  # the study trains its own 'neural'
    labelled = StudyConfig(simulators=(f"other=neural:{ckpt}", "disk")).specs()
    assert [(label, spec.name) for label, spec in labelled] == [("other", "neural"), ("disk", "disk")]
    with pytest.raises(BadInputError, match="not found"):
        StudyConfig(simulators=("x=diagnosed:missing.json",)).specs()
    with pytest.raises(BadInputError, match="at least one seed"):
        StudyConfig(seeds=()).specs()


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
