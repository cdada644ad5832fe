"""Processing of raw capture sessions into the processed dataset format v1 (paper sections 3.4 to 3.7)."""
