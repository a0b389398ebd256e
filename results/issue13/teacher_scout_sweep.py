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

    cd results/issue13 && ../../.venv/bin/python teacher_scout_sweep.py CONFIG MODE@SWEEP[@WALL[@CLEAR]] [...]

``--no-bars``: without the first two lines (the classical team, the teacher with Lloyd's step alone). ``WALL``: the
sweep only at least that far plus 0.3 m from every wall, fading to none at it
(``ClassicalPursuers.scout_sweep_wall``; empty: everywhere); ``CLEAR``: only at least that far plus 0.3 m from every
evader (``ClassicalPursuers.scout_sweep_clear``).
"""
import dataclasses
import sys

from _layered import VALIDATION, LayeredClassical, print_suite_line
from training.baselines import ClassicalPursuers
from training.config import ExperimentConfig
from training.train import teacher_pursuers


def teacher(cfg: ExperimentConfig, mode: str = "heading", sweep: float | None = None,
            wall: float | None = None, clear: float | None = None) -> LayeredClassical:
    """The config's teacher (``training.train.teacher_pursuers``) with the sweep's options replaced, flown through the
    config's layer; ``wall`` (``ClassicalPursuers.scout_sweep_wall``) has no ``[train]`` option."""
    t = LayeredClassical(cfg.spec)
    t.c = teacher_pursuers(dataclasses.replace(cfg.train, teacher_scout_sweep=sweep, teacher_scout_sweep_mode=mode,
                                               teacher_scout_sweep_clear=clear))
    t.c.scout_sweep_wall = wall
    return t


cfg = ExperimentConfig.from_toml(sys.argv[1])
print(f"{cfg.name}: avoidance {cfg.spec.avoidance}; evaluation seeds {VALIDATION['seeds']} pooled; "
      "min distance [m] / tracking / coverage")
args = [a for a in sys.argv[2:] if a != "--no-bars"]
if "--no-bars" not in sys.argv:  # the bars are already in the file this run's lines go to
    print_suite_line(cfg, "classical team (no layer)", ClassicalPursuers, 200, coverage=True, **VALIDATION)
    print_suite_line(cfg, "teacher, Lloyd's step", lambda: teacher(cfg), 200, coverage=True, **VALIDATION)
for arg in args:
    mode, sweep, *rest = arg.split("@")
    wall = float(rest[0]) if rest and rest[0] else None
    clear = float(rest[1]) if len(rest) > 1 else None
    print_suite_line(cfg, f"teacher, Lloyd's step + {mode} {float(sweep):g}"
                     + (f", at least {wall:g} + 0.3 m from every wall" if wall is not None else "")
                     + (f", at least {clear:g} + 0.3 m from every evader" if clear is not None else ""),
                     lambda: teacher(cfg, mode, float(sweep), wall, clear), 200, coverage=True, **VALIDATION)
