"""Format v1: round trip, and one test per validation failure the reader must report."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile

from dp5k_common.dataset import DatasetReader, PairParams, copy_pairs, split_scenes, write_index, write_pair
from dp5k_common.errors import DatasetFormatError
from dp5k_testing.tiny_dataset import make_arrays, make_params, make_tiny_dataset


@pytest.fixture()
def ds(tmp_path: Path) -> Path:
    make_tiny_dataset(tmp_path / "ds")
    return tmp_path / "ds"


def pair_dir(ds: Path) -> Path:
    return ds / "pairs" / "s0_cam0_f1.8"


def test_round_trip_preserves_values_units_and_params(tmp_path: Path) -> None:
    params = make_params("p1", extra_key="kept")
    arrays = make_arrays(params)
    write_pair(tmp_path, params, **arrays)
    write_index(tmp_path, {"train": ["p1"], "val": [], "test": []}, note="x")
    reader = DatasetReader(tmp_path)
    assert reader.extra == {"note": "x"}
    pair = reader.load("p1")
    np.testing.assert_allclose(pair.sharp, arrays["sharp"], atol=0.5 / 65535 + 1e-7)
    np.testing.assert_allclose(pair.left, arrays["left"], atol=0.5 / 65535 + 1e-7)
    assert pair.sharp.dtype == np.float32 and pair.sharp.shape == (16, 24, 3)
    np.testing.assert_array_equal(pair.depth_mm, np.rint(arrays["depth_mm"]))
    assert np.isnan(pair.coc_px[0, 0]) and not pair.valid[0, 0]
    valid = pair.valid
    np.testing.assert_allclose(pair.coc_px[valid], arrays["coc_px"][valid], rtol=1e-6)
    assert pair.params == params
    assert pair.params.extra == {"extra_key": "kept"}
    # Stored files are exactly the documented types.
    raw = cv2.imread(str(tmp_path / "pairs/p1/sharp.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape == (16, 24, 3)
    coc = tifffile.imread(tmp_path / "pairs/p1/coc.tif")
    assert coc.dtype == np.float32 and coc.ndim == 2


def test_colour_order_is_rgb_on_disk(tmp_path: Path) -> None:
    params = make_params("p1")
    arrays = make_arrays(params)
    arrays["sharp"] = np.zeros_like(arrays["sharp"])
    arrays["sharp"][..., 0] = 1.0  # pure red
    write_pair(tmp_path, params, **arrays)
    from PIL import Image

    rgb = np.asarray(Image.open(tmp_path / "pairs/p1/sharp.png"))
    # PIL may reduce 16-bit RGB to 8-bit on some versions; red must be the first channel either way.
    assert rgb[..., 0].min() > 0 and rgb[..., 1].max() == 0 and rgb[..., 2].max() == 0


def test_write_refuses_to_overwrite_and_leaves_no_temp(tmp_path: Path) -> None:
    params = make_params("p1")
    write_pair(tmp_path, params, **make_arrays(params))
    with pytest.raises(DatasetFormatError, match="already exists"):
        write_pair(tmp_path, params, **make_arrays(params))
    bad = make_arrays(params)
    bad["left"] = bad["left"][:, :10]
    with pytest.raises(DatasetFormatError, match="left"):
        write_pair(tmp_path, make_params("p2"), **bad)
    assert sorted(p.name for p in (tmp_path / "pairs").iterdir()) == ["p1"]


def test_missing_dataset_json(tmp_path: Path) -> None:
    (tmp_path / "pairs").mkdir()
    with pytest.raises(DatasetFormatError, match="dataset.json"):
        DatasetReader(tmp_path)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: d.update(format="other"), "'format'"),
        (lambda d: d.update(version=2), "unsupported version"),
        (lambda d: d["splits"].pop("val"), "lacks val"),
        (lambda d: d["splits"]["test"].append("nope"), "unknown pair id 'nope'"),
        (lambda d: d["splits"]["val"].extend(d["splits"]["train"]), "listed twice"),
    ],
)
def test_bad_index(ds: Path, mutate, match: str) -> None:
    index = json.loads((ds / "dataset.json").read_text())
    mutate(index)
    (ds / "dataset.json").write_text(json.dumps(index))
    with pytest.raises(DatasetFormatError, match=match):
        DatasetReader(ds)


@pytest.mark.parametrize("name", ["sharp.png", "left.png", "right.png", "depth.png", "coc.tif", "params.json"])
def test_missing_file_names_pair_and_file(ds: Path, name: str) -> None:
    (pair_dir(ds) / name).unlink()
    with pytest.raises(DatasetFormatError) as err:
        DatasetReader(ds).load("s0_cam0_f1.8")
    assert "s0_cam0_f1.8" in str(err.value) and name in str(err.value) and "missing" in str(err.value)


def test_wrong_dtype_8bit_view(ds: Path) -> None:
    img = cv2.imread(str(pair_dir(ds) / "left.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(pair_dir(ds) / "left.png"), (img >> 8).astype(np.uint8))
    with pytest.raises(DatasetFormatError, match=r"left.png.*16-bit"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_wrong_channel_count_gray_sharp(ds: Path) -> None:
    img = cv2.imread(str(pair_dir(ds) / "sharp.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(pair_dir(ds) / "sharp.png"), img[..., 0])
    with pytest.raises(DatasetFormatError, match=r"sharp.png.*3 channels"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_wrong_channel_count_rgb_depth(ds: Path) -> None:
    d = cv2.imread(str(pair_dir(ds) / "depth.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(pair_dir(ds) / "depth.png"), np.dstack([d, d, d]))
    with pytest.raises(DatasetFormatError, match=r"depth.png.*single-channel"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_wrong_dtype_coc(ds: Path) -> None:
    coc = tifffile.imread(pair_dir(ds) / "coc.tif")
    tifffile.imwrite(pair_dir(ds) / "coc.tif", coc.astype(np.float64))
    with pytest.raises(DatasetFormatError, match=r"coc.tif.*float32"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_shapes_disagree_between_files(ds: Path) -> None:
    img = cv2.imread(str(pair_dir(ds) / "right.png"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(pair_dir(ds) / "right.png"), img[:-2])
    with pytest.raises(DatasetFormatError, match=r"right.png.*disagrees"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_coc_nan_where_depth_valid(ds: Path) -> None:
    coc = tifffile.imread(pair_dir(ds) / "coc.tif")
    coc[3, 3] = np.nan
    tifffile.imwrite(pair_dir(ds) / "coc.tif", coc)
    with pytest.raises(DatasetFormatError, match=r"coc.tif.*NaN"):
        DatasetReader(ds).load("s0_cam0_f1.8")


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("f_number", None, "missing key"),
        ("f_number", "1.8", "must be a number"),
        ("focus_distance_mm", float("nan"), "not finite"),
        ("pixel_pitch_mm", -1.0, "must be > 0"),
        ("focal_length_mm", 5000.0, "must exceed"),
        ("focus_point_px", [1.0], "list of 2"),
        ("image_size", [24.5, 16], "positive integers"),
        ("pair_id", "other", "folder is"),
        ("scene", "", "non-empty string"),
        ("sharp_f_number", -22.0, "must be >= 0"),
        ("sharp_f_number", "f/22", "must be a number"),
    ],
)
def test_bad_params(ds: Path, key: str, value, match: str) -> None:
    path = pair_dir(ds) / "params.json"
    params = json.loads(path.read_text())
    if value is None:
        params.pop(key)
    else:
        params[key] = value
    path.write_text(json.dumps(params))
    with pytest.raises(DatasetFormatError, match=match) as err:
        DatasetReader(ds).load("s0_cam0_f1.8")
    assert "params.json" in str(err.value)


def test_malformed_params_json(ds: Path) -> None:
    (pair_dir(ds) / "params.json").write_text("{not json")
    with pytest.raises(DatasetFormatError, match="not valid JSON"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_corrupt_png(ds: Path) -> None:
    (pair_dir(ds) / "sharp.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(DatasetFormatError, match=r"sharp.png.*cannot decode"):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_split_scenes_is_deterministic_and_disjoint() -> None:
    scenes = [f"scene{i:03d}" for i in range(40)]
    a = split_scenes(scenes, seed=3)
    assert a == split_scenes(list(reversed(scenes)), seed=3)
    assert sorted(a["train"] + a["val"] + a["test"]) == scenes
    assert (len(a["train"]), len(a["val"]), len(a["test"])) == (30, 5, 5)
    assert split_scenes(["a", "b", "c"])["val"] and split_scenes(["a", "b", "c"])["test"]


def test_params_json_roundtrip_rejects_bool() -> None:
    obj = make_params("p").to_json()
    obj["f_number"] = True
    with pytest.raises(DatasetFormatError):
        PairParams.from_json(obj, "x")


@pytest.mark.parametrize(
    "keys, match",
    [
        ({"crop_origin_px": [0, 0]}, "needs 'full_image_size' too"),
        ({"full_image_size": [96, 64]}, "needs 'crop_origin_px' too"),
        ({"crop_origin_px": [0.5, 0], "full_image_size": [96, 64]}, "'crop_origin_px' must be a list of 2 integers"),
        ({"crop_origin_px": [0, 0], "full_image_size": "96x64"}, "'full_image_size' must be a list of 2 integers"),
        ({"crop_origin_px": [80, 0], "full_image_size": [96, 64]}, "does not fit"),
        ({"crop_origin_px": [-1, 0], "full_image_size": [96, 64]}, "does not fit"),
    ],
)
def test_bad_tile_geometry_is_refused(ds: Path, keys: dict, match: str) -> None:
    """A tile's place in its frame sets the field coordinates diagnose fits with: malformed, it is an error."""
    path = pair_dir(ds) / "params.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **keys}))
    with pytest.raises(DatasetFormatError, match=match):
        DatasetReader(ds).load("s0_cam0_f1.8")


def test_tile_geometry_reads_back(ds: Path) -> None:
    reader = DatasetReader(ds)
    assert reader.load("s0_cam0_f1.8").params.frame_geometry == ((0, 0), (24, 16))
    path = pair_dir(ds) / "params.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), "crop_origin_px": [8, 4], "full_image_size": [96, 64]}))
    assert DatasetReader(ds).load("s0_cam0_f1.8").params.frame_geometry == ((8, 4), (96, 64))


def test_copy_pairs_resplits_a_copy_resumes_and_leaves_the_source_alone(ds: Path, tmp_path: Path) -> None:
    src = DatasetReader(ds)
    train = src.ids("train")
    before = (ds / "dataset.json").read_bytes()
    out = tmp_path / "copy"
    (out / "pairs" / f".{train[0]}.partial").mkdir(parents=True)  # an interrupted copy left this
    copy_pairs(ds, out, {"train": train[1:], "val": [], "test": train[:1]}, source="held-out part")
    got = DatasetReader(out)
    assert got.ids("test") == train[:1] and got.ids("train") == train[1:] and got.extra["source"] == "held-out part"
    assert got.load(train[0]).left.tolist() == src.load(train[0]).left.tolist()
    assert not list((out / "pairs").glob(".*")) and (ds / "dataset.json").read_bytes() == before
    with pytest.raises(DatasetFormatError, match="no pair 'nope'"):
        copy_pairs(ds, tmp_path / "bad", {"train": ["nope"], "val": [], "test": []})
