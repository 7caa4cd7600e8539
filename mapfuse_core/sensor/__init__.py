"""Sensor data types below every subpackage that reads them: the laser and its scans."""

from mapfuse_core.sensor.laser import MAX_ANGLE_SIGMA, MAX_BEAMS, LaserParams, Scan

__all__ = ["MAX_ANGLE_SIGMA", "MAX_BEAMS", "LaserParams", "Scan"]
