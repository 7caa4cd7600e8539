"""SE(2) geometry and the map features' measurement models
(``docs/method.md`` §1–2).
"""
