"""DP simulators behind one interface: ``simulate(batch) -> (left, right)``."""
