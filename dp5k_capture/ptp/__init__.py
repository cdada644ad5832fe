"""PTP (ISO 15740) over USB, written here: containers, datasets, transport, sessions, typed errors."""
