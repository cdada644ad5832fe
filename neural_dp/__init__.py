"""DP simulators being judged and their commands: the handcrafted peers, the physical base model (with the effect
components diagnose extends it by), the Neural DP Simulator; ``dp5k train``, ``evaluate`` and ``synthesize``.

Other stages use this package only through :mod:`neural_dp.registry` (simulators by ``--simulator`` spec, the
base model's parts, fine-tuning, synthesis); the training tools it shares with them are :mod:`dp5k_learn`'s.
This package never imports the simulated world (``dp5k_studio``); it sees data only through the dataset format
v1 (``dp5k_common.dataset``).
"""
