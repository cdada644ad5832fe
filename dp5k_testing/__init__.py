"""Test support that ships with dp5k: the tests and the benchmarks both build their inputs with it.

* :mod:`.tiny_dataset`: tiny valid format-v1 datasets without the studio.
* :mod:`.foreign_dp`: a DP renderer and dataset writer that share no code with dp5k (per-pixel scattered
  half discs, its own scenes, its own formula for each effect), so diagnose is checked on data it did not make.
* :mod:`.aperture_dp` (scenes in :mod:`.aperture_scene`): a second one that discretises the other way round (the
  lens aperture sampled, a z-buffer per sub-aperture view, so occlusion is physical), with its own scenes, effect
  physics and sensor noise; ``write_matrix_cell`` writes one small confusion-matrix cell.
* :mod:`.pupil_dp` (scenes in :mod:`.pupil_scene`): a third one, held out from diagnose's tuning (only its benchmark
  results are to be looked at): PSFs from a sampled pupil function and layered "over" occlusion, its own effect
  physics and sensor noise, the same ``write_dataset`` convention.
* :mod:`.procam_synth`: a board or a projector image seen by a pinhole camera (processing unit tests).
* :mod:`.torchrun`: a ``dp5k`` command run as torchrun ranks on the CPU (sharding tests and benchmarks).
* :mod:`.sim_session`, :mod:`.truth`: a small simulated raw capture session written with the virtual studio
  (``dp5k process``), and its ground truth seen the way processing sees it.

Nothing in the pipeline imports this package; it sits on top, beside ``dp5k_demo``.
"""
