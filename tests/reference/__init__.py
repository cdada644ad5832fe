"""Reference implementations, kept once: one readable version per algorithm, named for the algorithm.

Every faster version in the packages is tested against its reference (``tests/process/test_reference_equivalence.py``,
``tests/studio/test_reference_equivalence.py``, ``tests/neural_dp/test_renderer_equivalence.py``). A speed pass
changes the package, never the reference, so the tests fail whenever a faster version changes an output. Where
only a reference's outputs matter, small golden outputs are kept instead (``make_golden.py``). Slow by design: do
not optimise these. Not test modules.
"""
