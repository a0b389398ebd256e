"""Scouts that keep moving: the twenty-ninth attempt's ten-iteration ES kept every pursuit pair but left training
seed 0's coverage below the classical team's, and neither more ES for the scouts nor a larger coverage weight gave it
back without losing a pursuit pair. The scouts' teacher is Lloyd's step, which settles each scout at its cell's
centroid, while coverage counts every cell seen over the episode. Here a wish of size ``SWEEP`` is added to Lloyd's
step (``ClassicalPursuers.scout_sweep``): "orbit", counter-clockwise about the arena's centre, or "heading", along the
scout's own velocity; both read only what a scout observes (its own position or velocity), so a feed-forward student
could learn them. The config's teacher (side lead and the rest of ``[train]``'s teacher options, push
``train.teacher_separation_gain``) flown through the config's avoidance layer, on validation episodes (evaluation seeds
100 and 101 pooled, 200 episodes each per kind, the scripted fleeing evaders added), with each kind's coverage; the
classical team first, as the bar. See results/README.md, thirtieth attempt.

    cd results/issue13 && ../../.venv/bin/python teacher_scout_sweep.py CONFIG MODE@SWEEP [MODE@SWEEP ...]
"""
import sys

from _layered import VALIDATION, LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers
from training.config import ExperimentConfig


def teacher(cfg: ExperimentConfig, mode: str | None = None, sweep: float | None = None) -> LayeredClassical:
    tc = cfg.train
    t = LayeredClassical(cfg.spec, tc.teacher_separation_gain)
    t.c.lead_side_time, t.c.lead_side_angle, t.c.lead_side_wall = (tc.teacher_side_lead, tc.teacher_side_angle,
                                                                    tc.teacher_side_wall)
    if mode is not None:
        t.c.scout_sweep, t.c.scout_sweep_mode = sweep, mode
    return t


cfg = ExperimentConfig.from_toml(sys.argv[1])
print(f"{cfg.name}: avoidance {cfg.spec.avoidance}; evaluation seeds {VALIDATION['seeds']} pooled; "
      "min distance [m] / tracking / coverage")
print_suite_line(cfg, "classical team (no layer)", ClassicalPursuers, 200, coverage=True, **VALIDATION)
print_suite_line(cfg, "teacher, Lloyd's step", lambda: teacher(cfg), 200, coverage=True, **VALIDATION)
for arg in sys.argv[2:]:
    mode, sweep = arg.split("@")
    print_suite_line(cfg, f"teacher, Lloyd's step + {mode} {float(sweep):g}", lambda: teacher(cfg, mode, float(sweep)),
                     200, coverage=True, **VALIDATION)
