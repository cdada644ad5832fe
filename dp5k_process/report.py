"""Per-scene report pictures: the contact sheet (sharp, left, right, depth, CoC per camera), shared with the
importers in :mod:`dp5k_common.preview`."""

from dp5k_common.preview import contact_sheet

__all__ = ["contact_sheet"]
