"""The shared learning layer: what every trained network of dp5k uses, whatever it learns.

The format-v1 torch Dataset and its batches (:mod:`.data`, :mod:`.batch`), masked losses and metrics
(:mod:`.losses`, :mod:`.metrics`), checkpoints (:mod:`.checkpoint`), the process group and device under
``torchrun`` (:mod:`.distributed`), the run's set-up and its one optimiser step (:mod:`.setup`), the epoch loop
with resume, validation and best/last checkpoints (:mod:`.epochs`), the config sections and their TOML /
override loader (:mod:`.config`) and the command-line options every training command shares
(:mod:`.cli_options`). ``dp5k train`` (``neural_dp``) and ``dp5k deblur train`` (``dp5k_deblur``) keep only
their network's forward pass and loss.

This package imports no stage: only ``dp5k_common``, torch, numpy and click.
"""
