"""Capture: PTP/USB and the Canon EOS extension, ESC/VP21, pattern display, the capture sequence and the raw session."""
