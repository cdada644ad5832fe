"""``dp5k demo``: the whole pipeline on the virtual studio, through the same code paths as the real commands,
ending in a report a researcher would want to read."""
