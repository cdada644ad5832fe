"""Shared test helpers (tiny data makers). Not a test module."""
