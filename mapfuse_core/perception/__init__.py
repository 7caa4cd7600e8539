"""Feature extraction from laser scans (``docs/method.md`` §2)."""
