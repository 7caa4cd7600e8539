"""Measurement logs and the real datasets (``docs/log-format.md``,
``docs/datasets.md``).
"""
