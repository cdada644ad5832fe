"""The demo's stage runner: reuse of finished stages, failures that name the stage and the fix."""

from __future__ import annotations

from pathlib import Path

import pytest

from dp5k_common.errors import BadInputError, StageError
from dp5k_demo.stages import Stage, run_stages


def counting_stage(name: str, calls: list[str], *, fail: Exception | None = None, always: bool = False) -> Stage:
    def run(ctx: dict) -> dict:
        calls.append(name)
        if fail is not None:
            raise fail
        return {"value": len(calls), "saw": sorted(ctx["results"])}

    return Stage(name, name.title(), run, f"do X for {name}", always=always)


def test_finished_stages_are_reused_and_results_flow(tmp_path: Path) -> None:
    calls: list[str] = []
    stages = [counting_stage("a", calls), counting_stage("b", calls), counting_stage("r", calls, always=True)]
    first = run_stages(stages, {}, tmp_path)
    assert calls == ["a", "b", "r"] and first["b"]["result"]["saw"] == ["a"]
    second = run_stages(stages, {}, tmp_path)
    assert calls == ["a", "b", "r", "r"]  # only the always-stage ran again
    assert second["a"]["reused"] and second["b"]["reused"] and not second["r"]["reused"]
    assert second["b"]["result"] == first["b"]["result"]


def test_failure_names_stage_and_fix_and_keeps_earlier_stages(tmp_path: Path) -> None:
    calls: list[str] = []
    stages = [counting_stage("a", calls), counting_stage("b", calls, fail=ValueError("boom")), counting_stage("c", calls)]
    with pytest.raises(StageError) as err:
        run_stages(stages, {}, tmp_path)
    assert err.value.exit_code == 7
    assert "demo stage 'b'" in str(err.value) and "boom" in str(err.value) and "fix: do X for b" in str(err.value)
    assert calls == ["a", "b"]
    assert (tmp_path / ".stages" / "a.json").is_file() and not (tmp_path / ".stages" / "b.json").exists()
    # a fixed stage resumes where the run stopped
    stages[1] = counting_stage("b", calls)
    run_stages(stages, {}, tmp_path)
    assert calls == ["a", "b", "b", "c"]


def test_dp5k_errors_keep_their_message(tmp_path: Path) -> None:
    stages = [counting_stage("a", [], fail=BadInputError("file is bad", where="x.png"))]
    with pytest.raises(StageError, match=r"x.png: file is bad; fix: do X for a"):
        run_stages(stages, {}, tmp_path)
