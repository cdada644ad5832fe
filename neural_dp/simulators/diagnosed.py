"""The ``diagnosed`` simulator: the physical base model extended with the effects a ``dp5k diagnose`` report fitted.

``dp5k synthesize --simulator diagnosed:REPORT.json`` renders with the base model's fitted parameters plus each
named effect's component and fitted parameters, read from the report's ``"extended_model_spec"``
(:mod:`neural_dp.simulators.base.spec`). This closes the loop: measured data -> named causes -> a calibrated
simulator -> training data. The prediction is the noise-free expectation (a fitted ``noise`` component is kept
in the model but adds nothing, as in the base model).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import ClassVar

from dp5k_common.errors import BadInputError

from .base import BaseModel
from .base.spec import model_from_spec

SPEC_KEY = "extended_model_spec"


class DiagnosedSimulator(BaseModel):
    """A :class:`BaseModel` rebuilt from a diagnose report; see the module docstring."""

    name: ClassVar[str] = "diagnosed"

    @classmethod
    def from_report(cls, report: str | os.PathLike[str]) -> DiagnosedSimulator:
        """Read ``report`` (a diagnose report.json) and rebuild its extended model.

        Raises:
            BadInputError: missing or unreadable file, no ``extended_model_spec`` key, or a malformed spec.
        """
        path = Path(report)
        if not path.is_file():
            raise BadInputError("diagnose report not found", where=path)
        try:
            data = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise BadInputError(f"not a JSON report ({exc})", where=path) from exc
        if not isinstance(data, dict) or SPEC_KEY not in data:
            raise BadInputError(f"no '{SPEC_KEY}' in this report; re-run 'dp5k diagnose' to write one", where=path)
        try:
            return model_from_spec(data[SPEC_KEY], cls)  # type: ignore[return-value]
        except BadInputError as exc:
            raise BadInputError(f"{SPEC_KEY}: {exc.message}", where=path) from exc
