"""The classical team with and without the learned actors' avoidance layer (runtime.avoidance), against the
scripted fleeing evaders and each kind of the held-out suite (the same episodes: evaluation seed 0): what the layer
alone costs a team that pursues like the classical one. Min distance [m] / tracking, captures and team contacts
per episode.

    .venv/bin/python results/issue13/classical_layer.py [CONFIG] [EPISODES]     (configs/role_based.toml, 100)
"""
import sys
from _layered import LayeredClassical
from training.baselines import ClassicalPursuers, TeamPolicy, FleeingEvaders
from training.config import ExperimentConfig
from training.evader_suite import make_suite_evader, SUITE
from training.evaluate import evaluate

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100

for kind in ["scripted"] + list(SUITE):
    row = []
    for name, team in (("classical", ClassicalPursuers()), ("classical+layer", LayeredClassical(cfg.spec))):
        ev = FleeingEvaders() if kind == "scripted" else make_suite_evader(kind, 0)
        m = evaluate(cfg, TeamPolicy(team, ev), eps, seed=0, progress=False)
        row.append(f"{name} {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} cap {m['captures_per_episode']:.2f} tc {m['team_contacts_per_episode']:.2f}")
    print(f"{kind:11s} " + "   ".join(row), flush=True)
