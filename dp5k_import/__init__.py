"""Import dual-pixel data into dataset format v1 (``dp5k import``): a stage of its own.

An *adapter* turns one source layout into :class:`SceneSource` objects, each of which loads its scene's
:class:`Capture` objects (sharp, left, right as linear float images on one exposure scale, a depth map and the
imaging parameters) only when written; :func:`write_imported` optionally tiles each capture into pairs (useful
when a dataset has few, large frames), keeps the source's splits or splits by scene, writes the dataset atomically
pair by pair, and reports a malformed scene without losing the others. :data:`IMPORTERS` lists the adapters by
name (dp5k release, Sdirt DP119, DPDD, generic folders); docs/data-format.md gives each source layout.
"""

from .capture import Capture, SceneSource, decode_curve, read_rgb8
from .dp5k_release import dp5k_sources
from .dpdd import dpdd_sources
from .exposure import Exposure, measure_exposure
from .generic import generic_sources
from .sdirt import sdirt_captures, sdirt_sources
from .sources import IMPORTERS, import_dataset
from .writer import write_imported

__all__ = [
           "IMPORTERS",
           "Capture",
           "Exposure",
           "SceneSource",
           "decode_curve",
           "dp5k_sources",
           "dpdd_sources",
           "generic_sources",
           "import_dataset",
           "measure_exposure",
           "read_rgb8",
           "sdirt_captures",
           "sdirt_sources",
           "write_imported",
]
