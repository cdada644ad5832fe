"""Shared foundation of dp5k: errors, units and optics, atomic I/O and the dataset format v1.

Every other package (capture, the studio, processing, the simulators, diagnose) may import this one;
this one imports none of them.
"""

__version__ = "0.1.0"
