"""DP simulators being judged: the handcrafted peers, the physical base model and the Neural DP Simulator.

This package never imports the simulated world (``dp5k_capture.sim``); it sees data only through the
dataset format v1 (``dp5k_common.dataset``).
"""
