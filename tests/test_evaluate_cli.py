"""``swarm-train evaluate``: the command as a user runs it (a subprocess), its JSON and its errors."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cli_fixtures import in_process
from runtime.metrics import METRIC_KEYS

ROOT = Path(__file__).resolve().parent.parent
REQUIRED = ["episodes", "mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
            "collisions_per_episode"]


def swarm_train(*args: str) -> subprocess.CompletedProcess:
    """``swarm-train ARGS`` in a fresh interpreter (the console script's entry point), from the repo root."""
    return subprocess.run([sys.executable, "-c", "import sys; from training.cli import main; sys.exit(main())",
                           *args], cwd=ROOT, capture_output=True, text=True, timeout=120)


def _check_metrics(doc: dict, episodes: int) -> None:
    for k in REQUIRED:
        assert k in doc, f"missing {k}"
    assert set(METRIC_KEYS) <= set(doc)
    assert doc["episodes"] == episodes
    hw = 3.0
    diag = 2 * hw * 2 ** 0.5
    assert 0 <= doc["mean_min_dist"] <= doc["mean_avg_dist"] <= doc["mean_max_dist"] <= diag
    assert 0 <= doc["tracking_rate"] <= 1 and 0 < doc["coverage"] <= 1
    assert doc["collisions_per_episode"] >= 0


@pytest.mark.parametrize("policy, config", [("random", "configs/multi_target.toml"),
                                            ("classical", "configs/role_based.toml")])
def test_evaluate_writes_the_json_and_prints_the_table(tmp_path, policy, config):
    out = tmp_path / "sub" / f"{policy}.json"
    r = swarm_train("evaluate", "--config", config, "--policy", policy, "--episodes", "4", "--seed", "3",
                    "--n-envs", "2", "--json", str(out), "--no-progress")
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    _check_metrics(doc, 4)
    assert doc["policy"] == policy and doc["seed"] == 3 and doc["config"] == Path(config).stem
    assert len(doc["spec_hash"]) >= 8
    # the printed table carries the same numbers, beside the paper's
    assert "tracking rate" in r.stdout and "paper" in r.stdout
    assert f"{doc['mean_min_dist']:.4f}" in r.stdout
    assert f"wrote {out}" in r.stdout


def test_same_seed_same_numbers_other_seed_other_numbers(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    docs = []
    for i, seed in enumerate(["5", "5", "6"]):
        p = tmp_path / f"{i}.json"
        rc, _, err = in_process(capsys, "evaluate", "--policy", "classical", "--episodes", "3", "--seed", seed,
                                "--n-envs", "3", "--json", str(p), "--no-progress")
        assert rc == 0, err
        docs.append({k: json.loads(p.read_text())[k] for k in METRIC_KEYS})
    assert docs[0] == docs[1]
    assert docs[0] != docs[2]


def test_plot_option_writes_a_png(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    png = tmp_path / "ep.png"
    rc, out, err = in_process(capsys, "evaluate", "--policy", "random", "--episodes", "1", "--n-envs", "1",
                              "--plot", str(png), "--no-progress")
    assert rc == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"wrote {png}" in out


@pytest.mark.parametrize("args, needle", [
    (["--episodes", "0"], "--episodes: expected a whole number in 1..1000000"),
    (["--episodes", "many"], "expected a whole number"),
    (["--policy", "smart"], "invalid choice: 'smart'"),
    (["--config", "configs/nope.toml"], "does not exist"),
])
def test_bad_arguments_exit_2_with_one_clear_line(capsys, monkeypatch, args, needle):
    monkeypatch.chdir(ROOT)
    rc, _, err = in_process(capsys, "evaluate", *args, "--no-progress")
    assert rc == 2
    assert needle in err and "Traceback" not in err


def test_bad_config_value_names_the_field(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[spec.team]\nn_pursuers = -2\n')
    rc, _, err = in_process(capsys, "evaluate", "--config", str(bad), "--episodes", "1", "--no-progress")
    assert rc == 2 and "Traceback" not in err
    assert "spec.team.n_pursuers" in err and err.startswith("swarm-train evaluate: error:")


# ---- the split collisions, the held-out suite, user evaders, several runs --------------------------------

SPLIT = ["teammate_contacts_per_episode", "team_obstacle_contacts_per_episode", "evader_contacts_per_episode"]


def _check_split(doc: dict) -> None:
    assert doc["collisions_per_episode"] == pytest.approx(sum(doc[k] for k in SPLIT))
    assert doc["team_contacts_per_episode"] == pytest.approx(doc[SPLIT[0]] + doc[SPLIT[1]])


def test_classical_vs_the_suite_reports_each_kind_and_their_mean(tmp_path, capsys, monkeypatch):
    from training.evader_suite import SUITE
    monkeypatch.chdir(ROOT)
    out, md = tmp_path / "suite.json", tmp_path / "suite.md"
    rc, stdout, err = in_process(capsys, "evaluate", "--policy", "classical", "--evader", "suite", "--episodes", "2",
                                 "--n-envs", "2", "--seed", "4", "--json", str(out), "--md", str(md), "--no-progress")
    assert rc == 0, err
    doc = json.loads(out.read_text())
    assert set(doc) == {*SUITE, "suite_mean"}
    for kind in SUITE:
        _check_metrics(doc[kind], 2)
        _check_split(doc[kind])
        assert doc[kind]["evader"] == f"suite:{kind}"
    mean = doc["suite_mean"]
    assert mean["episodes"] == 2 * len(SUITE)
    assert mean["mean_min_dist"] == pytest.approx(np.mean([doc[k]["mean_min_dist"] for k in SUITE]))
    assert "classical vs suite mean" in stdout and "team-obstacle contacts" in stdout
    assert "| teammate_contacts_per_episode |" in md.read_text()
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]  # written via a temporary file


def test_evader_lists_combine_kinds_in_order():
    from training.evader_spec import expand
    from training.evader_suite import SUITE
    assert expand("all") == ["learned", "scripted", *(f"suite:{k}" for k in SUITE)]
    assert expand("scripted+suite:hider+both") == ["scripted", "suite:hider", "learned"]
    assert expand("suite:juker,wanderer") == ["suite:juker", "suite:wanderer"]


def test_one_suite_kind_gives_a_flat_document(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    out = tmp_path / "w.json"
    rc, _, err = in_process(capsys, "evaluate", "--evader", "suite:wanderer", "--episodes", "2", "--n-envs", "2",
                            "--json", str(out), "--no-progress")
    assert rc == 0, err
    doc = json.loads(out.read_text())
    _check_metrics(doc, 2)
    assert doc["evader"] == "suite:wanderer" and doc["policy"] == "classical"


USER_EVADER = '''
import numpy as np

class Circling:
    """Every evader flies a circle; records the seed it was built with."""
    def __init__(self, seed=None):
        self.seed = seed
        self.t = 0

    def act(self, obs, env):
        self.t += 1
        a = np.zeros((obs.shape[0], env.n_agents, 2))
        a[:, env.spec.team.n_team:] = [np.cos(0.2 * self.t), np.sin(0.2 * self.t)]
        return a

class WrongShape:
    def act(self, obs, env):
        return np.zeros((obs.shape[0], 2))

class NoAct:
    pass
'''


def test_a_users_evader_class_from_a_file_or_a_module(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    f = tmp_path / "my_evaders.py"
    f.write_text(USER_EVADER)
    docs = {}
    for spec in (f"{f}:Circling", "my_evaders:Circling"):
        monkeypatch.syspath_prepend(str(tmp_path))
        out = tmp_path / f"{len(docs)}.json"
        rc, stdout, err = in_process(capsys, "evaluate", "--evader", spec, "--episodes", "2", "--n-envs", "2",
                                     "--seed", "2", "--json", str(out), "--no-progress")
        assert rc == 0, err
        docs[spec] = json.loads(out.read_text())
        _check_metrics(docs[spec], 2)
        assert docs[spec]["evader"] == spec and spec in stdout
    a, b = docs.values()
    assert a["mean_min_dist"] == b["mean_min_dist"]  # the same class either way
    rc, _, err = in_process(capsys, "evaluate", "--evader", "scripted", "--episodes", "2", "--n-envs", "2",
                            "--seed", "2", "--json", str(tmp_path / "s.json"), "--no-progress")
    assert json.loads((tmp_path / "s.json").read_text())["mean_min_dist"] != a["mean_min_dist"]


@pytest.mark.parametrize("spec, needle", [
    ("{d}/nothere.py:X", "no file"),
    ("{d}/my_evaders.py:Missing", "has no 'Missing'"),
    ("{d}/my_evaders.py:NoAct", "has no act(obs, env) method"),
    ("{d}/my_evaders.py:WrongShape", "act returned shape"),
    ("no_such_module_xyz:X", "cannot import 'no_such_module_xyz'"),
    ("fleeing", "is not an evader"),
    ("suite:nope", "unknown suite kind nope"),
    ("learned", "needs the co-trained evaders"),
    ("scripted+nope", "in it, 'nope' is not an evader"),
])
def test_bad_evader_specs_exit_2_with_one_line_naming_the_option(tmp_path, capsys, monkeypatch, spec, needle):
    monkeypatch.chdir(ROOT)
    (tmp_path / "my_evaders.py").write_text(USER_EVADER)
    value = spec.format(d=tmp_path)
    rc, _, err = in_process(capsys, "evaluate", "--evader", value, "--episodes", "1", "--n-envs", "1",
                            "--no-progress")
    assert rc == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert needle in err and "--evader" in err and value in err


def test_models_vs_both_keeps_its_layout_with_the_split(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    out = tmp_path / "both.json"
    rc, stdout, err = in_process(capsys, "evaluate", "--models", "models/role_based", "--evader", "both",
                                 "--episodes", "2", "--n-envs", "2", "--json", str(out), "--no-progress")
    assert rc == 0, err
    doc = json.loads(out.read_text())
    assert set(doc) == {"learned", "scripted"}
    for kind in doc:
        _check_metrics(doc[kind], 2)
        _check_split(doc[kind])
        _check_split(doc[kind]["classical"])
    assert "ours vs learned" in stdout and "classical vs scripted" in stdout


def test_several_runs_give_mean_and_min_max_beside_the_classical_team(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    out, md = tmp_path / "agg.json", tmp_path / "agg.md"
    rc, stdout, err = in_process(capsys, "evaluate", "--models", "models/paper_role_based", "--models",
                                 "models/role_based_int*", "--evader", "scripted", "--episodes", "2", "--n-envs", "2",
                                 "--seed", "1", "--json", str(out), "--md", str(md), "--no-progress")
    assert rc == 0, err
    doc = json.loads(out.read_text())
    assert doc["sources"] == ["models/paper_role_based", "models/role_based_int8"]
    e = doc["evaders"]["scripted"]
    assert len(e["runs"]) == 2
    for k in ("mean_min_dist", "tracking_rate", *SPLIT):
        vals = [r[k] for r in e["runs"]]
        assert e["min"][k] == min(vals) and e["max"][k] == max(vals)
        assert e["mean"][k] == pytest.approx(np.mean(vals))
    # the classical team ran once on the same evaders and seeds: the same as evaluating it alone
    single = tmp_path / "cl.json"
    in_process(capsys, "evaluate", "--evader", "scripted", "--episodes", "2", "--n-envs", "2", "--seed", "1",
               "--json", str(single), "--no-progress")
    assert e["classical"]["mean_min_dist"] == json.loads(single.read_text())["mean_min_dist"]
    text = md.read_text()
    assert text == stdout[:len(text)]
    assert "as close and tracking as often (runs of 2)" in text and "| scripted |" in text
    assert "team contacts <= classical (runs of 2)" in text
    assert f"{e['mean']['mean_min_dist']:.3f} [{e['min']['mean_min_dist']:.3f}-{e['max']['mean_min_dist']:.3f}]" in text


def test_a_glob_that_matches_nothing_is_an_error(capsys, monkeypatch):
    monkeypatch.chdir(ROOT)
    rc, _, err = in_process(capsys, "evaluate", "--run", "runs/none_such_*", "--no-progress")
    assert rc == 2 and "matches no folder" in err


def test_run_counts_compare_each_run_with_the_classical_team_on_its_evaders():
    from training.aggregate import fewer_contacts, markdown, spread, wins

    def m(d, t, c):
        return {"mean_min_dist": d, "tracking_rate": t, "team_contacts_per_episode": c, "coverage": 0.5,
                "teammate_contacts_per_episode": c / 2, "team_obstacle_contacts_per_episode": c / 2,
                "evader_contacts_per_episode": 0.0, "captures_per_episode": 1.0}
    runs = [m(0.4, 0.5, 1.0), m(0.6, 0.5, 0.1), m(0.4, 0.2, 0.3)]
    scripted = {"runs": runs, **spread(runs), "classical": m(0.5, 0.4, 0.3)}
    # co-trained evaders differ per run: each run meets the classical team on its own evaders
    own = [m(0.3, 0.6, 0.0), m(0.7, 0.6, 0.2), m(0.5, 0.1, 0.4)]
    learned = {"runs": runs, **spread(runs), "classical": {"runs": own, **spread(own)}}
    assert (wins(scripted), fewer_contacts(scripted)) == (1, 2)  # run 0 closer and tracking more; runs 1, 2
    assert (wins(learned), fewer_contacts(learned)) == (1, 2)  # run 2 (0.4 <= 0.5, 0.2 >= 0.1); runs 1, 2
    assert spread(runs)["min"]["mean_min_dist"] == 0.4 and spread(runs)["max"]["tracking_rate"] == 0.5
    doc = {"config": "x", "sources": ["a", "b", "c"], "episodes": 5, "seed": 1, "eval_seed_offset": 10,
           "evaders": {"scripted": scripted, "learned": learned}}
    text = markdown(doc)
    assert "| scripted | 0.467 [0.400-0.600] | 0.500 |" in text and text.count("| 1/3 | 2/3 |") == 2


def test_plot_draws_the_learned_team_and_refuses_several_teams(tmp_path, capsys, monkeypatch):
    """``--plot`` with ``--run``/``--models`` draws one episode of that team (it was silently ignored); with
    several teams it is a usage error before any episode runs."""
    monkeypatch.chdir(ROOT)
    png = tmp_path / "episode.png"
    rc, stdout, err = in_process(capsys, "evaluate", "--models", "models/role_based", "--evader", "suite:hider",
                                 "--episodes", "1", "--n-envs", "1", "--plot", str(png), "--no-progress")
    assert rc == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert f"wrote {png}" in stdout
    other = tmp_path / "two.png"
    rc, _, err = in_process(capsys, "evaluate", "--models", "models/role_based", "--models", "models/paper_role_based",
                            "--episodes", "1", "--n-envs", "1", "--plot", str(other), "--no-progress")
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--plot" in err and "one --run or --models" in err
    assert not other.exists()
