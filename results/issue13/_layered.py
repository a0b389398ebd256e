"""The classical team flown through the learned actors' avoidance layer, for the issue-13 scripts beside this file
(classical_layer.py, layer_params.py, teacher_layer.py, teacher_lead.py, teacher_pincer.py, wall_probe.py), and the
suite line that teacher_lead.py and teacher_pincer.py print."""
from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from runtime.avoidance import avoid_agents, avoid_rows, role_tables
from runtime.spec import SwarmSpec
from training.baselines import ClassicalPursuers, FleeingEvaders, TeamPolicy
from training.evader_suite import SUITE, make_suite_evader
from training.evaluate import evaluate, mean_of


VALIDATION = {"seeds": (100, 101), "scripted": True, "digits": 4}
"""``print_suite_line``'s keywords for the validation episodes that choose a teacher (evaluation seeds 100 and 101
pooled, the scripted fleeing evaders added, four decimals), kept apart from the seeds that report results (0, 1, 2)."""


class LayeredClassical:
    """``ClassicalPursuers`` (teammate push ``separation_gain``; None: its own) with every team action through the
    avoidance layer of ``spec``. ``tables``: a function editing the kernel's ``(params, layout)`` before each use,
    for a diagnostic no spec can express."""

    def __init__(self, spec: SwarmSpec, separation_gain: float | None = None,
                 tables: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None) -> None:
        self.c = ClassicalPursuers()
        if separation_gain is not None:
            self.c.separation_gain = separation_gain
        self.spec, self.tables, self.team = spec, tables, np.arange(spec.team.n_team)

    def act(self, obs: np.ndarray, env: Any) -> np.ndarray:
        a = self.c.act(obs, env)
        if self.tables is None:
            return avoid_agents(self.spec, obs, a, self.team)
        for i in self.team:
            params, layout = self.tables(*role_tables(self.spec, self.spec.roles[i]))
            col = np.ascontiguousarray(a[:, i], dtype=np.float64)
            avoid_rows(obs[:, i], col, params, layout)
            a[:, i] = col
        return a


def print_suite_line(cfg: Any, label: str, make: Callable[[], Any], episodes: int, seeds: Sequence[int] = (0,),
                     scripted: bool = False, digits: int = 3, coverage: bool = False) -> None:
    """Fly a team from ``make()`` (a new one per kind and seed) against every held-out suite kind, ``episodes``
    episodes each per evaluation seed in ``seeds`` (default: seed 0 alone; several: their episodes pooled, each seed's
    scripted kinds drawing their parameters from it, as ``swarm-train evaluate --seed S`` does), and print one line:
    the suite mean and each kind's min distance [m] / tracking, to ``digits`` decimals; ``scripted``: the scripted
    fleeing evaders last; ``coverage``: each kind's coverage after its tracking, and the mean over the kinds."""
    kinds = list(SUITE) + (["scripted"] if scripted else [])

    def evader(kind: str, seed: int) -> Any:
        return FleeingEvaders() if kind == "scripted" else make_suite_evader(kind, seed)

    per = {kind: mean_of([evaluate(cfg, TeamPolicy(make(), evader(kind, seed)), episodes, seed=seed, progress=False)
                          for seed in seeds]) for kind in kinds}
    m = mean_of([per[kind] for kind in SUITE])

    def cov(v: dict) -> str:
        return f"/{v['coverage']:.{digits}f}" if coverage else ""
    print(f"{label}: suite {m['mean_min_dist']:.{digits}f}/{m['tracking_rate']:.{digits}f} "
          f"tc {m['team_contacts_per_episode']:.2f}"
          + (f" coverage {mean_of(list(per.values()))['coverage']:.{digits}f}" if coverage else "") + "   "
          + "  ".join(f"{k} {v['mean_min_dist']:.{digits}f}/{v['tracking_rate']:.{digits}f}{cov(v)}"
                      for k, v in per.items()), flush=True)


def print_validation_bars(cfg: Any, teacher_label: str = "teacher (lead 0.6 s)", episodes: int = 200) -> None:
    """The first lines of every teacher probe on the validation episodes (``VALIDATION``): the config's layer, then
    the classical team (the bar) and the config's teacher (push ``train.teacher_separation_gain``, flown through the
    layer) under ``teacher_label``."""
    print(f"{cfg.name}: avoidance {cfg.spec.avoidance}; evaluation seeds {VALIDATION['seeds']} pooled")
    print_suite_line(cfg, "classical team (lead 0.6 s, push 3, no layer)", ClassicalPursuers, episodes, **VALIDATION)
    print_suite_line(cfg, teacher_label, lambda: LayeredClassical(cfg.spec, cfg.train.teacher_separation_gain),
                     episodes, **VALIDATION)
