"""Simulated devices (Canon EOS body, EPSON projector) and the virtual studio they render through."""
