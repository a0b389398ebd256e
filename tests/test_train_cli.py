"""``swarm-train train`` / ``evaluate --run`` / ``plot --run`` as a user runs them: end to end in subprocesses
with tiny budgets, checkpoint/resume, stop-with-checkpoint, and config errors that name the field."""
from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli_fixtures import in_process
from runtime.metrics import METRIC_KEYS

ROOT = Path(__file__).resolve().parent.parent
REQUIRED = ["episodes", "mean_min_dist", "mean_avg_dist", "mean_max_dist", "tracking_rate", "coverage",
            "collisions_per_episode"]

TINY = """name = "multi_target"
[spec.team]
n_pursuers = 2
n_scouts = 0
n_evaders = 1
[train]
n_envs = 4
batch_size = 32
buffer_size = 5000
warmup_steps = 20
noise_decay_steps = 100
log_every = 50
checkpoint_every = 100
threads = 1
"""


def swarm_train(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "import sys; from training.cli import main; sys.exit(main())",
                           *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def _rows(run: Path) -> list[dict]:
    with (run / "metrics.csv").open() as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("train")
    cfg = d / "tiny.toml"
    cfg.write_text(TINY)
    run = d / "run"
    r = swarm_train("train", "--config", str(cfg), "--out", str(run), "--steps", "150", "--seed", "3",
                    "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "finished at env step 150" in r.stdout
    return run


def test_train_writes_a_complete_run_folder(tiny_run):
    run = tiny_run
    for name in ("config.toml", "run.json", "metrics.csv", "summary.json", "actors.pt", "checkpoints/state.pt",
                 "checkpoints/buffer.pt", "train.log"):
        assert (run / name).is_file(), name
    meta = json.loads((run / "run.json").read_text())
    assert meta["git_revision"] != "" and "spec_hash" in meta
    assert "--steps" in meta["command"]
    cfg_text = (run / "config.toml").read_text()
    assert "seed = 3" in cfg_text and "steps = 150" in cfg_text  # overrides recorded
    rows = _rows(run)
    assert [int(r["step"]) for r in rows] == [50, 100, 150]
    last = rows[-1]
    assert int(last["frames"]) == 150 * 4 and int(last["updates"]) > 0
    assert float(last["min_dist"]) <= float(last["avg_dist"]) <= float(last["max_dist"])
    assert float(last["reward_pursuer"]) != 0 and last["reward_scout"] == ""
    assert list((run / "tb").glob("events.out.tfevents.*"))
    summary = json.loads((run / "summary.json").read_text())
    assert summary["env_steps"] == 150 and summary["fps"] > 0 and summary["updates_per_s"] > 0


def test_resume_continues_the_run_exactly_where_it_stopped(tiny_run, tmp_path):
    import shutil

    import torch
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    before = torch.load(run / "checkpoints" / "state.pt", weights_only=False)
    r = swarm_train("train", "--out", str(run), "--resume", "--steps", "200", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "finished at env step 200" in r.stdout
    after = torch.load(run / "checkpoints" / "state.pt", weights_only=False)
    assert before["env_step"] == 150 and after["env_step"] == 200
    assert after["agent"]["updates"] == before["agent"]["updates"] + 50  # one update per step, buffer kept
    assert [int(x["step"]) for x in _rows(run)] == [50, 100, 150, 200]
    meta = json.loads((run / "run.json").read_text())
    assert meta["resumed"][0]["at_step"] == 150
    # the actors changed (training went on)
    w0 = before["agent"]["actors"]["weights.0"]
    assert not torch.equal(w0, after["agent"]["actors"]["weights.0"])
    # resuming a finished run with no more steps changes nothing and says so
    r = swarm_train("train", "--out", str(run), "--resume", "--no-progress")
    assert r.returncode == 0, r.stderr


def test_a_full_disk_keeps_the_last_checkpoint_whole_and_says_so_in_one_line(tiny_run, tmp_path, capsys,
                                                                               monkeypatch):
    """torch reports a full disk as a RuntimeError from its zip writer, after it wrote part of the file: the run
    stops with one line that names the file, the free space and the fix, and the checkpoint it had is untouched
    (state and buffer of the same step, no partial file beside them)."""
    import shutil

    import training.checkpoint
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    ckpt = run / "checkpoints"
    before = {p.name: p.read_bytes() for p in [*ckpt.iterdir(), run / "actors.pt"]}
    real_save = training.checkpoint.torch.save

    def full_disk(obj, f, *args, **kwargs):
        if str(f).endswith("state.pt.tmp"):
            Path(f).write_bytes(b"PK\x03\x04 half a zip")
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(training.checkpoint.torch, "save", full_disk)
    rc, _, err = in_process(capsys, "train", "--out", str(run), "--resume", "--steps", "200", "--no-progress")
    assert rc == 1
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("swarm-train train: failed: ")
    assert "state.pt" in err and "MB free there" in err
    assert "train.checkpoint_buffer = false" in err and "--resume" in err
    assert "unexpected pos" in err  # what torch said, kept
    assert {p.name: p.read_bytes() for p in [*ckpt.iterdir(), run / "actors.pt"]} == before
    assert not list(run.rglob("*.tmp"))
    monkeypatch.setattr(training.checkpoint.torch, "save", real_save)
    rc, out, err = in_process(capsys, "train", "--out", str(run), "--resume", "--steps", "200", "--no-progress")
    assert rc == 0, err  # once there is room again, it resumes from the kept checkpoint
    assert "finished at env step 200" in out


def test_init_from_fine_tunes_another_run_under_a_new_config(tiny_run, tmp_path):
    import torch
    cfg = tmp_path / "int8.toml"
    cfg.write_text(TINY.replace("threads = 1", "threads = 1\nint8_robustness = 30.0\nseed = 3"))
    run = tmp_path / "ft"
    r = swarm_train("train", "--config", str(cfg), "--init-from", str(tiny_run), "--out", str(run), "--steps", "200",
                    "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "finished at env step 200" in r.stdout
    src = torch.load(tiny_run / "checkpoints" / "state.pt", weights_only=False)
    st = torch.load(run / "checkpoints" / "state.pt", weights_only=False)
    assert st["agent"]["updates"] == src["agent"]["updates"] + 50  # it went on from the source's networks
    assert json.loads((run / "run.json").read_text())["init_from"] == {"run": str(tiny_run), "at_step": 150}
    rows = _rows(run)
    assert [int(x["step"]) for x in rows] == [200] and float(rows[-1]["int8_sensitivity"]) > 0
    assert _rows(tiny_run)[-1]["int8_sensitivity"] == ""  # not logged when the penalty is off
    assert "int8_robustness = 30.0" in (run / "config.toml").read_text()
    # errors name the fix: nothing left to train, both flags, a source without a checkpoint
    r = swarm_train("train", "--config", str(cfg), "--init-from", str(tiny_run), "--out", str(tmp_path / "x"),
                    "--steps", "150", "--no-progress")
    assert r.returncode == 2 and "already at env step 150" in r.stderr and "train.steps" in r.stderr
    r = swarm_train("train", "--init-from", str(tiny_run), "--out", str(run), "--resume", "--no-progress")
    assert r.returncode == 2 and "exclude each other" in r.stderr
    r = swarm_train("train", "--config", str(cfg), "--init-from", str(tmp_path / "nowhere"), "--out",
                    str(tmp_path / "y"), "--no-progress")
    assert r.returncode == 2 and "state.pt does not exist" in r.stderr


def test_sigterm_stops_with_a_checkpoint_that_resumes(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    run = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-c", "import sys; from training.cli import main; sys.exit(main())",
                          "train", "--config", str(cfg), "--out", str(run), "--steps", "1000000", "--no-progress"],
                         cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 90
        while time.time() < deadline and not (run / "metrics.csv").is_file() or len(_rows(run)) < 1:
            assert time.time() < deadline and p.poll() is None, p.communicate()
            time.sleep(0.2)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    assert "interrupted at env step" in out and "--resume" in out
    import torch
    st = torch.load(run / "checkpoints" / "state.pt", weights_only=False)
    assert 50 <= st["env_step"] < 1000000
    assert (run / "actors.pt").is_file()


def test_evaluate_run_writes_the_metric_keys(tiny_run, tmp_path):
    out = tmp_path / "eval.json"
    r = swarm_train("evaluate", "--run", str(tiny_run), "--episodes", "4", "--n-envs", "2", "--seed", "5",
                    "--evader", "scripted", "--json", str(out), "--no-progress")
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    for k in REQUIRED:
        assert k in doc, k
    assert set(METRIC_KEYS) <= set(doc)
    assert doc["episodes"] == 4 and doc["evader"] == "scripted" and doc["seed"] == 5
    assert doc["eval_seed_offset"] > doc["seed"]  # held-out seeds: disjoint from training seeds
    assert set(REQUIRED) <= set(doc["classical"])
    assert "paper" in r.stdout and "classical vs scripted" in r.stdout
    assert f"{doc['mean_min_dist']:.4f}" in r.stdout


def test_plot_run_draws_curves_and_a_snapshot(tiny_run, tmp_path):
    r = swarm_train("plot", "--run", str(tiny_run), "--out", str(tmp_path / "figs"))
    assert r.returncode == 0, r.stderr
    for name in ("rewards.png", "distances.png", "episode.png"):
        p = tmp_path / "figs" / name
        assert p.is_file() and p.stat().st_size > 5000, name
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("line, field", [("update_every = 0", "train.update_every"),
                                         ("evaders = \"sleepy\"", "train.evaders"),
                                         ("learning_rate = 0.1", "learning_rate"),
                                         ("gamma = 1.5", "train.gamma")])
def test_config_errors_name_the_field(tmp_path, capsys, line, field):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(TINY + line + "\n")
    rc, _, err = in_process(capsys, "train", "--config", str(cfg), "--out", str(tmp_path / "run"), "--no-progress")
    assert rc == 2
    assert field in err and "Traceback" not in err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_run_folder_errors_say_what_to_do(tmp_path, capsys, tiny_run):
    rc, _, err = in_process(capsys, "train", "--out", str(tmp_path / "nothing"), "--resume")
    assert rc == 2 and "nothing to resume" in err
    rc, _, err = in_process(capsys, "train", "--config", str(ROOT / "configs" / "multi_target.toml"), "--out",
                            str(tiny_run))
    assert rc == 2 and "--resume" in err
    rc, _, err = in_process(capsys, "evaluate", "--run", str(tmp_path / "nothing"), "--episodes", "2")
    assert rc == 2 and "not a training run" in err
