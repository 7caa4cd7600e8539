"""Measurement logs and the real datasets (``docs/conventions.md``,
``docs/real-data.md``).
"""
