"""The classical team with weaker or shorter teammate separation, against the scripted fleeing evaders and each
kind of the held-out suite (the same episodes for every variant: evaluation seed 0): whether a teacher whose
crowding term is gentler (easier for a decentralized student to follow, ``label_source.py``) is still at least as
strong as the classical team, which is the bar. Min distance [m] / tracking, captures and team contacts per
episode; the last line per variant is the suite mean.

    .venv/bin/python results/issue13/classical_separation.py [CONFIG] [EPISODES]     (configs/role_based.toml, 100)
"""
import sys
from training.baselines import ClassicalPursuers, TeamPolicy, FleeingEvaders
from training.config import ExperimentConfig
from training.evader_suite import make_suite_evader, SUITE
from training.evaluate import evaluate, mean_of

cfg = ExperimentConfig.from_toml(sys.argv[1] if len(sys.argv) > 1 else "configs/role_based.toml")
eps = int(sys.argv[2]) if len(sys.argv) > 2 else 100
variants = {"default (reach 0.5 m, gain 3)": {}, "gain 1.5": {"separation_gain": 1.5},
            "gain 1": {"separation_gain": 1.0}, "reach 0.3 m": {"separation_reach": 0.3}}
def line(label: str, m: dict) -> str:
    return (f"  {label:11s} {m['mean_min_dist']:.3f}/{m['tracking_rate']:.3f} cap {m['captures_per_episode']:.2f} "
            f"tc {m['team_contacts_per_episode']:.2f}")


for name, attrs in variants.items():
    suite = []
    print(name, flush=True)
    for kind in ["scripted"] + list(SUITE):
        team = ClassicalPursuers()
        for k, v in attrs.items():
            setattr(team, k, v)
        ev = FleeingEvaders() if kind == "scripted" else make_suite_evader(kind, 0)
        m = evaluate(cfg, TeamPolicy(team, ev), eps, seed=0, progress=False)
        if kind != "scripted":
            suite.append(m)
        print(line(kind, m), flush=True)
    print(line("suite mean", mean_of(suite)), flush=True)
