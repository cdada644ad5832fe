"""docs/cli.md is generated from the commands' help and must not go stale."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_cli_reference_is_current() -> None:
    result = subprocess.run([sys.executable, str(ROOT / "scripts" / "gen_cli_doc.py"), "--check"], cwd=ROOT)
    assert result.returncode == 0, "docs/cli.md is stale: run `python scripts/gen_cli_doc.py`"
