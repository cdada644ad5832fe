"""Which simulator ``dp5k diagnose`` holds against the data: ``--model`` parsed once, at the CLI edge."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dp5k_common.errors import BadInputError

PEERS: tuple[str, ...] = ("disk", "butterworth", "raytrace")
"""The handcrafted peers of the registry (``neural_dp.simulators.registry``)."""
KINDS: tuple[str, ...] = ("base", *PEERS, "neural")
NEURAL_PREFIX = "neural:"


@dataclass(frozen=True)
class ModelSpec:
    """A parsed ``--model``: ``kind`` is ``base``, a peer or ``neural``; ``checkpoint`` is the Neural DP
    checkpoint for ``neural`` (None otherwise)."""

    kind: str = "base"
    checkpoint: Path | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise BadInputError(f"unknown model {self.kind!r} (base, disk, butterworth, raytrace or neural:CKPT)", where="--model")
        if (self.kind == "neural") != (self.checkpoint is not None):
            raise BadInputError("a checkpoint goes with the neural model only (neural:CKPT)", where="--model")

    @classmethod
    def parse(cls, text: str) -> ModelSpec:
        """``base``, ``disk``, ``butterworth``, ``raytrace`` or ``neural:CKPT``.

        Raises:
            BadInputError: an unknown name or an empty checkpoint path.
        """
        if text.startswith(NEURAL_PREFIX):
            path = text[len(NEURAL_PREFIX) :]
            if not path:
                raise BadInputError("neural:CKPT needs a checkpoint path", where="--model")
            return cls("neural", Path(path))
        if text == "neural" or text not in KINDS:
            raise BadInputError(f"unknown model {text!r} (base, disk, butterworth, raytrace or neural:CKPT)", where="--model")
        return cls(text)

    def __str__(self) -> str:
        return f"{NEURAL_PREFIX}{self.checkpoint}" if self.kind == "neural" else self.kind

    @property
    def is_base(self) -> bool:
        return self.kind == "base"

    @property
    def is_neural(self) -> bool:
        return self.kind == "neural"

    def folder_name(self) -> str:
        """A folder-safe name for the default report folder (``diagnose-<this>``)."""
        return str(self).replace(":", "_").replace("/", "_")

    def check_files(self) -> None:
        """Raises BadInputError when the Neural DP checkpoint is missing (before anything is computed or written)."""
        if self.checkpoint is not None and not self.checkpoint.is_file():
            raise BadInputError("Neural DP checkpoint not found", where=self.checkpoint)

    def load_peer(self):
        """The simulator from the registry (``neural`` loads the checkpoint); not for ``base``."""
        from neural_dp.simulators.registry import get_simulator

        if self.is_neural:
            return get_simulator("neural", checkpoint=str(self.checkpoint))
        return get_simulator(self.kind)
