"""One CLI convention (docs/cli.md, "Conventions"): --out, --device auto, --crop-size, --resume/--no-resume and
--overwrite; the old spellings still work and say what replaces them; evaluate's default; verify points to check."""

from __future__ import annotations

import json
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from dp5k_cli import COMMANDS, main
from dp5k_common.dataset import DatasetReader
from dp5k_testing.tiny_dataset import make_tiny_dataset

DEPRECATED = "is deprecated; use"
# every command that writes something, and the ones that run a network
WRITERS = {"capture", "process", "validate-depth", "sl-depth", "train", "evaluate", "synthesize", "diagnose", "import",
           "demo", "studio make-dataset", "studio render", "deblur train", "deblur evaluate", "study downstream"}
NETWORKS = {"train", "evaluate", "synthesize", "diagnose", "deblur train", "deblur evaluate", "study downstream"}


def all_commands() -> dict[str, click.Command]:
    ctx = click.Context(main)
    found: dict[str, click.Command] = {}
    for name in COMMANDS:
        cmd = main.get_command(ctx, name)
        assert cmd is not None
        if isinstance(cmd, click.Group):
            found.update({f"{name} {sub}": cmd.get_command(ctx, sub) for sub in cmd.list_commands(ctx)})
        else:
            found[name] = cmd
    return found


def run(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, list(args))
    return res.exit_code, res.output


def lines(text: str) -> list[str]:
    return [line for line in text.strip().splitlines() if line.strip()]


def test_every_writer_takes_out_and_no_positional_out() -> None:
    """The output is --out/-o wherever something is written; no command shows OUT among its arguments."""
    commands = all_commands()
    with_out = {name for name, cmd in commands.items()
                if any(isinstance(p, click.Option) and "--out" in p.opts and "-o" in p.opts for p in cmd.params)}
    assert with_out == WRITERS
    ctx = click.Context(main)
    for name, cmd in commands.items():
        usage = " ".join(cmd.collect_usage_pieces(ctx))
        assert "OUT" not in usage, (name, usage)


def test_device_is_auto_everywhere_a_network_runs() -> None:
    commands = all_commands()
    has_device = {name for name, cmd in commands.items() if any(p.name == "device" for p in cmd.params)}
    assert has_device == NETWORKS
    for name in NETWORKS:
        opt = next(p for p in commands[name].params if p.name == "device")
        # training commands leave the default to the config file, whose own default is auto
        assert opt.default == "auto" or (opt.default is None and name in ("train", "deblur train")), name
    from neural_dp.config import TrainConfig
    from dp5k_deblur.config import DeblurTrainConfig

    assert TrainConfig().device == "auto" and DeblurTrainConfig().device == "auto"


def test_a_device_that_is_not_one_is_a_one_line_error(tmp_path: Path) -> None:
    make_tiny_dataset(tmp_path / "ds", scenes=3)
    for args in (["evaluate", str(tmp_path / "ds"), "--device", "gpu"],
                 ["diagnose", str(tmp_path / "ds"), "--device", "cuda0"],
                 ["train", str(tmp_path / "ds"), "--device", "tpu"]):
        code, out = run(*args)
        assert code == 3 and len(lines(out)) == 1 and "--device must be one of auto|cpu|cuda|cuda:N" in out, (args, out)
    import torch

    if not torch.cuda.is_available():  # asked for a GPU this machine does not have: refused before any work
        code, out = run("evaluate", str(tmp_path / "ds"), "--simulator", "disk", "--out", str(tmp_path / "e"),
                        "--device", "cuda")
        assert code == 3 and "torch sees no CUDA device" in out and len(lines(out)) == 1, out
        assert not (tmp_path / "e").exists()


def test_old_positional_out_still_works_and_warns_after_the_output(tmp_path: Path) -> None:
    """studio make-dataset OUT (old) and --out OUT (new) write the same dataset; only the old one warns, once,
    after the command's own output."""
    common = ["--scenes", "1", "--size", "48x32", "--f-numbers", "4", "--seed", "3"]
    code, old = run("studio", "make-dataset", str(tmp_path / "old"), *common)
    assert code == 0, old
    note = "OUT as the last argument is deprecated; use --out OUT"
    assert lines(old)[-1].endswith(note) and old.count(DEPRECATED) == 1
    code, new = run("studio", "make-dataset", "--out", str(tmp_path / "new"), *common)
    assert code == 0 and DEPRECATED not in new, new
    code, short = run("studio", "make-dataset", "-o", str(tmp_path / "short"), *common)
    assert code == 0 and DEPRECATED not in short, short
    a, b = DatasetReader(tmp_path / "old"), DatasetReader(tmp_path / "new")
    assert a.ids() == b.ids() == DatasetReader(tmp_path / "short").ids() and len(a.ids()) == 2
    pid = a.ids()[0]
    assert (tmp_path / "old" / "pairs" / pid / "left.png").read_bytes() == (tmp_path / "new" / "pairs" / pid / "left.png").read_bytes()
    code, out = run("studio", "make-dataset", str(tmp_path / "x"), "--out", str(tmp_path / "y"), *common)
    assert code == 3 and "OUT given twice" in out and not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    code, out = run("studio", "make-dataset", *common)
    assert code == 2 and "Missing option '-o' / '--out'" in out


def test_a_failing_command_with_an_old_spelling_still_prints_one_line(tmp_path: Path) -> None:
    """The error policy holds with deprecated spellings: the note ends the one error line (issue 31's checks of
    import and sl-depth with OUT as the last argument)."""
    (tmp_path / "src").mkdir()
    afile = tmp_path / "afile"
    afile.write_text("x")
    for args in (["import", "generic", str(tmp_path / "src"), str(afile)],
                 ["sl-depth", str(tmp_path / "src"), str(tmp_path / "cal.yaml"), str(afile), "--projector", "64x32"]):
        code, out = run(*args)
        assert code == 3 and len(lines(out)) == 1, (args, out)
        assert out.startswith(f"dp5k: error: {afile}: not a folder") and "(also: OUT as the last argument is deprecated" in out
        code, out = run(*args[:3], "--out", str(afile), *args[4:])
        assert code == 3 and len(lines(out)) == 1 and DEPRECATED not in out, out


def test_synthesize_old_and_new_out(tmp_path: Path) -> None:
    from dp5k_demo.rgbd import write_rgbd_frames

    make_tiny_dataset(tmp_path / "ds", scenes=2, W=48, H=32)
    write_rgbd_frames(tmp_path / "ds", tmp_path / "frames", 2)
    args = ["--simulator", "disk", "--f-number", "2", "--encoding", "linear"]
    code, old = run("-q", "synthesize", str(tmp_path / "frames"), str(tmp_path / "old"), *args)
    assert code == 0 and "OUT as the last argument is deprecated" in old, old
    code, new = run("-q", "synthesize", str(tmp_path / "frames"), "--out", str(tmp_path / "new"), *args)
    assert code == 0 and DEPRECATED not in new, new
    assert DatasetReader(tmp_path / "old").ids() == DatasetReader(tmp_path / "new").ids() != []


def test_process_resume_vocabulary_and_old_out(tmp_path: Path) -> None:
    """process: --no-resume refuses an OUT holding processed scenes (named through the old positional OUT too);
    --overwrite is accepted; a missing RAW is still the first error."""
    out = tmp_path / "processed"
    (out / "reports" / "s0").mkdir(parents=True)
    (tmp_path / "raw").mkdir()
    code, msg = run("process", str(tmp_path / "raw"), str(out), "--no-resume")
    assert code == 3 and f"{out / 'reports'}: --no-resume but an earlier run's processed scenes is here" in msg, msg
    assert "OUT as the last argument is deprecated" in msg and len(lines(msg)) == 1
    code, msg = run("process", str(tmp_path / "raw"), "--out", str(out), "--no-resume")
    assert code == 3 and "--overwrite" in msg and DEPRECATED not in msg


def test_train_crop_size_and_its_old_spelling(tmp_path: Path) -> None:
    """--crop-size sets data.crop_px; the old --crop PX still does, with its line; both at once is refused."""
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3, W=48, H=32)
    tiny = ["--epochs", "1", "--batch-size", "1", "--device", "cpu", "--set", "model.base_channels=4",
            "--set", "model.levels=2", "--set", "data.samples_per_epoch=1"]
    code, out = run("-q", "train", str(ds), "--out", str(tmp_path / "new"), "--crop-size", "24", *tiny)
    assert code == 0 and DEPRECATED not in out, out
    code, out = run("-q", "train", str(ds), "--out", str(tmp_path / "old"), "--crop", "16", *tiny)
    assert code == 0 and "--crop PX (a training patch size) is deprecated; use --crop-size PX" in out, out
    assert json.loads((tmp_path / "new" / "config.json").read_text())["data"]["crop_px"] == 24
    assert json.loads((tmp_path / "old" / "config.json").read_text())["data"]["crop_px"] == 16
    code, out = run("train", str(ds), "--out", str(tmp_path / "both"), "--crop", "16", "--crop-size", "24")
    assert code == 3 and "--crop-size" in out and not (tmp_path / "both").exists()
    # --no-resume never touches an earlier run; --overwrite replaces it
    before = (tmp_path / "new" / "last.pt").read_bytes()
    code, out = run("train", str(ds), "--out", str(tmp_path / "new"), "--no-resume", *tiny)
    assert code == 3 and "--overwrite" in out and (tmp_path / "new" / "last.pt").read_bytes() == before
    code, out = run("-q", "train", str(ds), "--out", str(tmp_path / "new"), "--no-resume", "--overwrite",
                    "--crop-size", "16", *tiny)
    assert code == 0, out
    assert json.loads((tmp_path / "new" / "config.json").read_text())["data"]["crop_px"] == 16
    assert len(json.loads((tmp_path / "new" / "history.json").read_text())) == 1  # a fresh run, not a resumed one


def test_demo_force_is_overwrite_and_no_resume_refuses(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The demo's stage runner is replaced by a recorder here: only the mapping of the flags is under test (the
    real runner's reuse and rerun are tested in tests/demo)."""
    import dp5k_demo.cli as demo_cli

    seen: list[bool] = []

    def record(stages, ctx, out, *, force=False):  # noqa: ANN001, ANN202
        seen.append(force)
        return {"report": {"result": {"report": str(out / "report.html")}}}

    monkeypatch.setattr(demo_cli, "run_stages", record)
    out = tmp_path / "demo"
    (out / ".stages").mkdir(parents=True)
    (out / ".stages" / "capture.json").write_text("{}")
    code, msg = run("demo", "--out", str(out), "--no-resume")
    assert code == 3 and "--no-resume but an earlier demo run's finished stages" in msg and seen == []
    code, msg = run("demo", str(out), "--scale", "small")  # old positional OUT
    assert code == 0 and "OUT as the last argument is deprecated" in msg and seen == [False], msg
    code, msg = run("demo", "--out", str(out), "--force")
    assert code == 0 and "--force is deprecated; use --overwrite" in msg and seen[-1] is True, msg
    code, msg = run("demo", "--out", str(out), "--overwrite", "--no-resume")
    assert code == 0 and DEPRECATED not in msg and seen[-1] is True, msg


def test_evaluate_without_simulators_compares_every_available_one(tmp_path: Path) -> None:
    """No --simulator and no checkpoint: every simulator that needs none, exit 0 (the help's 'default')."""
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3, W=48, H=32)
    code, out = run("evaluate", str(ds), "--out", str(tmp_path / "e"), "--figures", "0")
    assert code == 0, out
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert metrics["simulators"] == ["disk", "butterworth", "raytrace", "base"]
    assert metrics["fit_pairs"] == min(8, len(DatasetReader(ds).ids("train"))) and "base" in metrics["fitted_parameters"]
    assert "no Neural DP checkpoint" in out
    code, out = run("evaluate", str(ds), "--out", str(tmp_path / "n"), "--simulator", "neural")  # named: required
    assert code == 3 and "dp5k train" in out and len(lines(out)) == 1


def test_evaluate_fit_pairs_sets_how_many_pairs_the_base_model_is_fitted_on(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=4, W=48, H=32)  # scenes 0 and 3 in train
    assert len(DatasetReader(ds).ids("train")) == 2
    code, out = run("evaluate", str(ds), "--out", str(tmp_path / "e"), "--simulator", "base", "--fit-pairs", "1",
                    "--figures", "0")
    assert code == 0, out
    metrics = json.loads((tmp_path / "e" / "metrics.json").read_text())
    assert metrics["fit_pairs"] == 1 and "base" in metrics["fitted_parameters"]


def test_verify_given_a_dataset_runs_check(tmp_path: Path) -> None:
    ds = tmp_path / "ds"
    make_tiny_dataset(ds, scenes=3)
    code, out = run("verify", str(ds))
    assert code == 0 and "running dp5k check" in out and "dp5k dataset v1, 3 pairs" in out, out
    (ds / "pairs" / "s1_cam0_f1.8" / "left.png").unlink()
    code, out = run("verify", str(ds))
    assert code == 4 and "left.png" in out
    (tmp_path / "empty").mkdir()
    code, out = run("verify", str(tmp_path / "empty"))
    assert code == 3 and "dp5k check DATASET" in out and len(lines(out)) == 1
