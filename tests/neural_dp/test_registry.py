"""One simulator spec for every command (``--simulator``), parsed once; the older flags still work and say what
replaces them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_cli import main
from dp5k_common.errors import BadInputError
from dp5k_testing.tiny_dataset import make_tiny_dataset
from neural_dp.registry import PEERS, SimulatorSpec, default_simulators


def test_specs_are_parsed_once_into_a_typed_spec(tmp_path: Path) -> None:
    assert SimulatorSpec.parse("base") == SimulatorSpec() and SimulatorSpec().is_base
    for name in PEERS:
        spec = SimulatorSpec.parse(name)
        assert spec.is_peer and spec.path is None and str(spec) == name
    ckpt = tmp_path / "run" / "best.pt"
    spec = SimulatorSpec.parse(f"neural:{ckpt}")
    assert spec.is_neural and spec.checkpoint == ckpt and str(spec) == f"neural:{ckpt}"
    assert SimulatorSpec.parse(str(spec)) == spec == SimulatorSpec.parse("neural", checkpoint=ckpt)
    report = SimulatorSpec.parse("diagnosed:rep/report.json")
    assert report.name == "diagnosed" and report.path == Path("rep/report.json") and report.checkpoint is None
    assert "/" not in spec.folder_name() and ":" not in spec.folder_name()
    assert [str(s) for s in default_simulators()] == [*PEERS, "base"]
    assert str(default_simulators(ckpt)[-1]) == f"neural:{ckpt}"


@pytest.mark.parametrize("bad,message", [("neural", "needs a checkpoint: neural:CKPT"), ("neural:", "needs a file path"),
                                         ("diagnosed", "needs a report: diagnosed:REPORT.json"), ("Base", "unknown simulator"),
                                         ("disk:x", "unknown simulator"), ("", "unknown simulator")])
def test_a_bad_spec_is_a_one_line_error_naming_the_syntax(bad: str, message: str) -> None:
    with pytest.raises(BadInputError, match=message):
        SimulatorSpec.parse(bad)


def test_a_missing_file_is_named_before_any_work(tmp_path: Path) -> None:
    with pytest.raises(BadInputError, match="Neural DP checkpoint not found"):
        SimulatorSpec.parse(f"neural:{tmp_path / 'a.pt'}").check_files()
    with pytest.raises(BadInputError, match="diagnose report not found"):
        SimulatorSpec.parse(f"diagnosed:{tmp_path / 'r.json'}").check_files()
    SimulatorSpec.parse("disk").check_files()  # names no file


def test_evaluate_takes_repeated_specs_and_the_older_flags_with_a_warning(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3)
    runner = CliRunner()
    res = runner.invoke(main, ["-q", "evaluate", str(ds), "--out", str(tmp_path / "new"), "--simulator", "disk",
                               "--simulator", "base", "--figures", "0"])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "new" / "metrics.json").read_text())["simulators"] == ["disk", "base"]
    res = runner.invoke(main, ["-q", "evaluate", str(ds), "--out", str(tmp_path / "old"), "--simulators", "disk,base",
                               "--figures", "0"])
    assert res.exit_code == 0, res.output
    assert "--simulators A,B is deprecated; use --simulator A --simulator B" in res.output
    assert json.loads((tmp_path / "old" / "metrics.json").read_text())["simulators"] == ["disk", "base"]
    res = runner.invoke(main, ["evaluate", str(ds), "--simulator", "disk", "--simulators", "base"])
    assert res.exit_code == 3 and "not both" in res.output
    res = runner.invoke(main, ["evaluate", str(ds), "--simulators", "neural", "--checkpoint", str(tmp_path / "none.pt")])
    assert res.exit_code == 3 and "--checkpoint CKPT is deprecated; use --simulator neural:CKPT" in res.output
    assert "Neural DP checkpoint not found" in res.output and "none.pt" in res.output


def test_synthesize_needs_a_simulator_and_maps_the_older_checkpoint_flag(tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(main, ["synthesize", str(tmp_path), str(tmp_path / "out")])
    assert res.exit_code == 3 and "--simulator is required" in res.output and "neural:CKPT" in res.output
    res = runner.invoke(main, ["synthesize", str(tmp_path), str(tmp_path / "out"), "--simulator", "neural",
                               "--checkpoint", str(tmp_path / "none.pt")])
    assert res.exit_code == 3 and "--checkpoint CKPT is deprecated" in res.output
    assert "Neural DP checkpoint not found" in res.output and not (tmp_path / "out").exists()


def test_the_study_maps_its_older_flags_onto_specs(tmp_path: Path) -> None:
    res = CliRunner().invoke(main, ["study", "downstream", str(tmp_path / "rgbd"), str(tmp_path / "measured"), "--out",
                                    str(tmp_path / "study"), "--simulators", "disk", "--neural-checkpoint",
                                    str(tmp_path / "none.pt")])
    assert res.exit_code == 3, res.output
    assert "--simulators A,B is deprecated" in res.output
    assert "--neural-checkpoint CKPT is deprecated; use --simulator neural:CKPT" in res.output
    assert "Neural DP checkpoint not found" in res.output and "none.pt" in res.output
    res = CliRunner().invoke(main, ["study", "downstream", str(tmp_path / "rgbd"), str(tmp_path / "measured"), "--out",
                                    str(tmp_path / "study"), "--simulator", "base", "--simulator", "base"])
    assert res.exit_code == 3 and "one label per simulator" in res.output
