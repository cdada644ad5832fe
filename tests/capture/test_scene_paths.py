"""Hostile scene names and unwritable ``--out`` folders are refused up front: one line, exit code 3, nothing written,
no device touched (the rig file names a serial port that does not exist: touching it would exit 5)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from dp5k_capture.paths import check_scene_name
from dp5k_cli import main
from dp5k_common.errors import BadInputError

HOSTILE = [".", "..", "../x", "../../etc", "a/b", "", "x" * 300, "a\x00b", "CON", "con", "nul.dng", "Com1", "LPT1.txt",
           "aux", "-rf", ".hidden", "scene.", "sp ace"]


def _rig(tmp_path: Path) -> Path:
    rig = tmp_path / "rig.toml"
    rig.write_text('[projector]\nport = "/nonexistent/ttyUSB9"\n')
    return rig


def _tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


@pytest.mark.parametrize("dry_run", [False, True])
@pytest.mark.parametrize("scene", HOSTILE, ids=lambda s: repr(s)[:12])
def test_hostile_scene_names_are_refused_and_nothing_is_written(tmp_path: Path, scene: str, dry_run: bool) -> None:
    work = tmp_path / "work"
    work.mkdir()
    rig = _rig(tmp_path)
    before = _tree(tmp_path)
    args = ["capture", "--scene", scene, "--out", str(work / "raw"), "--rig", str(rig), *(["--dry-run"] if dry_run else [])]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 3, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dp5k: error: --scene: scene name ")
    assert _tree(tmp_path) == before  # nothing written, not even the --out folder


def test_good_names_pass() -> None:
    for name in ("s0001", "demo01", "wall", "a.b-c_d", "CONSOLE", "com10", "x" * 100, "rand3"):
        assert check_scene_name(name) == name
    with pytest.raises(BadInputError, match=r"longer than 100 characters"):
        check_scene_name("x" * 101)
    with pytest.raises(BadInputError, match=r"reserved on Windows"):
        check_scene_name("PRN.tar.gz")


@pytest.mark.parametrize("dry_run", [False, True])
def test_unwritable_out_is_refused_before_any_device(tmp_path: Path, dry_run: bool) -> None:
    rig = _rig(tmp_path)
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, why in ((Path("/proc/dp5k-raw"), "cannot write into /proc"), (a_file / "raw", "is a file"),
                     (a_file, f"not a folder ({a_file} is a file)")):  # --out itself a file: ours, not click's usage error
        res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--rig", str(rig),
                                        *(["--dry-run"] if dry_run else [])])
        assert res.exit_code == 3, res.output  # a device touched first would exit 5 (no such serial port)
        assert why in res.output and "ttyUSB9" not in res.output and len(res.output.strip().splitlines()) == 1
        assert res.output.startswith("dp5k: error: ") and "Usage:" not in res.output
    assert not Path("/proc/dp5k-raw").exists()


def test_missing_out_is_created_only_for_a_real_run(tmp_path: Path) -> None:
    out = tmp_path / "new" / "raw"
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--sim", "--dry-run"])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "new").exists()
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--rig", str(_rig(tmp_path))])
    assert res.exit_code == 5 and "ttyUSB9" in res.output  # the folder was made, then the (missing) projector failed
    assert out.is_dir() and not any(out.iterdir())


def test_ctrl_c_at_the_board_prompt_says_what_was_kept(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """click.prompt turns Ctrl-C into Abort: the capture still ends with the one resume line and exit code 130."""
    import dp5k_capture.session_run as session_run

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(session_run, "capture_scene", interrupted)
    out = tmp_path / "raw"
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--sim"])
    assert res.exit_code == 130 and res.output.strip().splitlines() == [
        f"dp5k: interrupted: no file was captured in {out / 's1'}; run the same command again to resume"]
    import click

    def aborted(*args: object, **kwargs: object) -> None:
        raise click.exceptions.Abort()

    monkeypatch.setattr(session_run, "capture_scene", aborted)
    res = CliRunner().invoke(main, ["capture", "--scene", "s1", "--out", str(out), "--sim"])
    assert res.exit_code == 130 and "run the same command again to resume" in res.output and "Aborted" not in res.output
