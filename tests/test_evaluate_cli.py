"""``swarm-train evaluate``: the command as a user runs it (a subprocess), its JSON and its errors."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

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
    (["--episodes", "0"], "--episodes: must be >= 1"),
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
