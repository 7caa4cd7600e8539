"""Simulation: worlds, the laser, the vehicle, scenarios and the pipeline
(``docs/method.md`` §3).
"""
