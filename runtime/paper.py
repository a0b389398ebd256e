"""The paper's figures (Kouzeghar et al., Tables I-III, the coverage figure and the real-drone flight), the one
definition that evaluation (``training.evaluate``) and the ground station's demo print beside ours.

Keys are experiment config names (``ExperimentConfig.name``): the paper's exact settings
(``paper_role_based``, ``paper_multi_target``, ``paper_flight``) and our shipped settings of the same team
(``role_based``, ``multi_target``), which are compared with the same figures.
"""
from __future__ import annotations

from typing import Any

_MULTI_TARGET = {"mean_min_dist": 0.4616, "mean_avg_dist": 2.1048, "mean_max_dist": 3.8639}
"""Table II: 5 pursuers vs 2 evaders, multi-target MADDPG [m]."""
_ROLE_BASED = {"mean_min_dist": 0.4745, "mean_avg_dist": 2.2609, "mean_max_dist": 4.1233, "coverage": 0.35}
"""Table III and the coverage figure: 5 pursuers + 5 scouts vs 2 evaders, Role-based MADDPG [m, 1]."""
_FLIGHT = {"mean_avg_dist": 0.4983}
"""Section V: 6 Crazyflies (2 pursuers, 3 scouts, 1 evader), average pursuer-target distance from the UWB
readings of the real flight [m]."""

PAPER: dict[str, dict[Any, float]] = {
    "multi_target": _MULTI_TARGET, "paper_multi_target": _MULTI_TARGET,
    "role_based": _ROLE_BASED, "paper_role_based": _ROLE_BASED,
    "paper_flight": _FLIGHT,
    # Table I: mean minimum distance [m] of multi-target MADDPG against the number of pursuers (2 evaders)
    "table_i": {2: 0.6307, 3: 0.5481, 4: 0.5029, 5: 0.4616, 6: 0.4613},
}

FLIGHT_TEAM = (2, 3, 1)
"""The paper's flight team: (pursuers, scouts, evaders)."""
