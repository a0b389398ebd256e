"""Experiment configuration: one TOML file maps onto ``ExperimentConfig`` (unknown keys are errors).

```toml
name = "role_based"
[spec.team]        # runtime.spec.SwarmSpec tables: arena, pursuer, scout, evader, team, sensing, timing
n_pursuers = 5
[rewards]          # RewardConfig
collision_penalty = 10.0
[train]            # TrainConfig
steps = 200000
```
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from runtime.spec import SpecError, SwarmSpec, from_mapping, load_toml


@dataclass(frozen=True)
class RewardConfig:
    """Constants of the paper's equations (1)-(5) and Algorithm 1."""

    boundary_c1: float = 10.0
    """Cap c1 of the x boundary term -min(exp(3|x| - 9), c1) (eq. 1)."""
    boundary_c2: float = 10.0
    """Cap c2 of the y boundary term (eq. 1)."""
    boundary_gain: float = 3.0
    """The 3 in exp(3|x| - 9); the 9 is boundary_gain x arena half width (3 m), as in the paper."""
    collision_penalty: float = 10.0
    """c3 (eq. 2): subtracted for every other agent in contact (distance <= R_i + R_j), teammates and
    evader-evader pairs; pursuer-team/evader contacts are captures, rewarded below instead."""
    obstacle_penalty: float = 0.0
    """Subtracted while touching an obstacle (0 in the paper: obstacles are solid in the world)."""
    capture_reward: float = 20.0
    """CR_p (eq. 3): added to a pursuer for every evader it touches."""
    distance_weight: float = 1.0
    """DR_p (eq. 3) = -distance_weight x mean distance from the pursuer to the evaders [1/m]."""
    captured_penalty: float = 10.0
    """CR_e (eq. 4): subtracted from an evader for every pursuer or scout touching it."""
    exploration_weight: float = 1.0
    """E_i (eq. 5, Algorithm 1) = -exploration_weight x the largest bounded Voronoi cell area [1/m^2], every
    agent a seed."""

    def __post_init__(self) -> None:
        for name in ("boundary_c1", "boundary_c2", "boundary_gain", "collision_penalty", "obstacle_penalty",
                     "capture_reward", "distance_weight", "captured_penalty", "exploration_weight"):
            if not getattr(self, name) >= 0:
                raise SpecError(f"rewards.{name}: must be >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class TrainConfig:
    """Role-based MADDPG hyper-parameters (see training.maddpg)."""

    steps: int = 200_000
    """Environment steps per env to train for (total frames = steps x n_envs)."""
    n_envs: int = 64
    """Environments stepped in parallel."""
    seed: int = 0
    """Seed of the world, the networks and the replay sampling."""

    def __post_init__(self) -> None:
        for name in ("steps", "n_envs"):
            if getattr(self, name) < 1:
                raise SpecError(f"train.{name}: must be >= 1, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class ExperimentConfig:
    name: str = "default"
    """Short name used for run folders and reports."""
    spec: SwarmSpec = field(default_factory=SwarmSpec)
    rewards: RewardConfig = field(default_factory=RewardConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "config") -> "ExperimentConfig":
        return from_mapping(cls, data, where)

    @classmethod
    def from_toml(cls, path: str | Path) -> "ExperimentConfig":
        return from_mapping(cls, load_toml(path), Path(path).name)

    def to_dict(self) -> dict[str, Any]:
        import dataclasses
        return {"name": self.name, "spec": self.spec.to_dict(), "rewards": dataclasses.asdict(self.rewards),
                "train": dataclasses.asdict(self.train)}
