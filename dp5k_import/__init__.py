"""Import public dual-pixel data into dataset format v1 (``dp5k import``): a stage of its own.

An *adapter* turns one public layout into :class:`Capture` objects (full-frame sharp, left, right as linear
float images, a depth map and the imaging parameters); :func:`write_imported` optionally tiles each into
pairs (useful when a dataset has few, large frames), splits by scene and writes the dataset atomically
pair by pair. :data:`IMPORTERS` lists the adapters by name; docs/data-format.md gives each source layout.
"""

from .capture import Capture, read_rgb8, srgb_to_linear
from .sdirt import sdirt_captures
from .sources import IMPORTERS, import_dataset
from .writer import write_imported

__all__ = ["Capture", "IMPORTERS", "import_dataset", "read_rgb8", "sdirt_captures", "srgb_to_linear", "write_imported"]
