"""Reproducible studies built on the library (each a function of its config)."""
