"""``swarm-train sweep``: the sweep file's errors, a tiny sweep on local processes, and (slow) on local Ray."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from flight_fixtures import wait_until

from runtime.spec import SpecError
from training.sweep import SweepConfig, job_config

ROOT = Path(__file__).resolve().parents[1]


def _sweep_file(tmp_path: Path, extra: str = "", n_pursuers: str = "[1, 2]") -> Path:
    p = tmp_path / "sweep.toml"
    p.write_text(f"""base = "{ROOT / 'configs' / 'multi_target.toml'}"
n_pursuers = {n_pursuers}
seeds = [0]
out = "{tmp_path / 'runs'}"
eval_episodes = 2
{extra}
[train]
steps = 40
n_envs = 2
batch_size = 16
warmup_steps = 10
imitation_steps = 20
imitation_batch = 16
imitation_polish_steps = 20
es_iterations = 0
log_every = 20
checkpoint_every = 1000
threads = 1
""")
    return p


def test_job_configs_change_only_the_pursuer_count_and_seed(tmp_path):
    sweep = SweepConfig.from_toml(_sweep_file(tmp_path, n_pursuers="[2, 6]"))
    assert sweep.jobs() == [(2, 0), (6, 0)]
    base = job_config(sweep, 2, 0)
    six = job_config(sweep, 6, 7)
    assert base.spec.team.n_pursuers == 2 and six.spec.team.n_pursuers == 6
    assert six.spec.team.n_evaders == 2 and six.spec.team.n_scouts == 0
    assert six.train.seed == 7 and six.train.steps == 40 and six.name == "multi_target_np6"


@pytest.mark.parametrize("extra, n_p, field", [("", "[0, 2]", "n_pursuers"),
                                               ("eval_evader = \"smart\"", "[2]", "eval_evader"),
                                               ("colour = 1", "[2]", "colour")])
def test_sweep_file_errors_name_the_field(tmp_path, extra, n_p, field):
    with pytest.raises(SpecError, match=field):
        SweepConfig.from_toml(_sweep_file(tmp_path, extra, n_p))


def test_unknown_train_field_is_named(tmp_path):
    p = _sweep_file(tmp_path)
    p.write_text(p.read_text() + "learning_rate = 0.1\n")
    with pytest.raises(SpecError, match="train.learning_rate"):
        SweepConfig.from_toml(p)


def test_tiny_sweep_on_local_processes(tmp_path):
    p = _sweep_file(tmp_path)
    r = subprocess.run([sys.executable, "-c", "import sys; from training.cli import main; sys.exit(main())",
                        "sweep", "--config", str(p), "--workers", "2", "--json", str(tmp_path / "s.json")],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "s.json").read_text())
    assert [row["n_pursuers"] for row in doc["rows"]] == [1, 2]
    for row in doc["rows"]:
        assert row["env_steps"] == [40] and row["mean_min_dist"] > 0 and row["classical_mean_min_dist"] > 0
    assert doc["rows"][1]["paper_mean_min_dist"] == 0.6307  # Table I, n_p = 2
    assert (tmp_path / "runs" / "np2_s0" / "actors.pt").is_file()
    md = (tmp_path / "s.md").read_text()
    assert md.count("\n| ") == 3
    for row in doc["rows"]:
        assert row["min_min_dist"] == row["max_min_dist"] == row["mean_min_dist"]  # one seed
        assert 0 <= row["tracking_rate"] <= 1 and 0 <= row["classical_tracking_rate"] <= 1
        assert row["seeds_as_close"] == int(row["mean_min_dist"] <= row["classical_mean_min_dist"])
        assert f"| {row['n_pursuers']} | {row['mean_min_dist']:.4f} | {row['classical_mean_min_dist']:.4f} |" in md
    assert "| 2 |" in r.stdout
    assert "done: n_pursuers=1 seed=0: 40 env steps" in r.stdout  # the CLI prints what run_local echoes


@pytest.mark.slow  # starts a local Ray instance: 93 s of the suite; run by pytest -m slow
def test_tiny_sweep_on_a_local_ray_instance(tmp_path):
    pytest.importorskip("ray")
    p = _sweep_file(tmp_path, n_pursuers="[2]")
    r = subprocess.run([sys.executable, "-c", "import sys; from training.cli import main; sys.exit(main())",
                        "sweep", "--config", str(p), "--ray", "local"],
                       cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads((tmp_path / "runs" / "sweep.json").read_text())
    assert [row["n_pursuers"] for row in doc["rows"]] == [2]
    assert "on Ray at local" in r.stdout


SHIPPED_SWEEPS = sorted((ROOT / "configs").glob("sweep*.toml"))


def test_the_shipped_sweep_files_are_found():
    assert SHIPPED_SWEEPS, f"no sweep*.toml in {ROOT / 'configs'}: the test below would check nothing"


@pytest.mark.parametrize("path", SHIPPED_SWEEPS, ids=lambda p: p.name)
def test_shipped_sweep_files_build_every_job(path):
    sweep = SweepConfig.from_toml(path)
    assert sweep.jobs() == [(n, s) for n in (2, 3, 4, 5, 6) for s in sweep.seeds]  # Table I's n_p, every seed
    for n, seed in sweep.jobs():
        cfg = job_config(sweep, n, seed)
        assert cfg.spec.team.n_pursuers == n and cfg.train.seed == seed


def test_a_job_config_error_names_the_job_and_the_key_once(tmp_path):
    p = tmp_path / "sweep.toml"
    p.write_text(f'base = "{ROOT / "configs" / "multi_target.toml"}"\nn_pursuers = [2]\nseeds = [0]\n[train]\nsteps = 40\n')
    with pytest.raises(SpecError, match=r"^multi_target\.toml \(n_pursuers=2, seed=0\)\.train\.imitation_steps: "
                                        r"must be in \[0, train\.steps = 40\], got 5000$"):
        job_config(SweepConfig.from_toml(p), 2, 0)


def test_a_replay_buffer_too_big_to_allocate_is_refused_before_training():
    from training.config import MAX_BUFFER, TrainConfig
    with pytest.raises(SpecError, match=r"^train\.buffer_size: must be <= 5,000,000 transitions"):
        TrainConfig(buffer_size=MAX_BUFFER + 1)


def test_the_summary_gives_mean_and_spread_over_seeds_beside_the_classical_team(tmp_path):
    from training.sweep import summarize_sweep
    sweep = SweepConfig.from_toml(_sweep_file(tmp_path, n_pursuers="[2]"))

    def job(seed, ours, classical):
        return {"n_pursuers": 2, "seed": seed,
                "eval": {"mean_min_dist": ours, "mean_avg_dist": 2.0, "tracking_rate": 0.5},
                "classical": {"mean_min_dist": classical, "tracking_rate": 0.4},
                "train": {"train_time_s": 100.0 + seed, "env_steps": 40, "fps": 1.0}}

    doc, md = summarize_sweep(sweep, [job(0, 0.5, 0.6), job(1, 0.7, 0.6), job(2, 0.6, 0.6)])
    (row,) = doc["rows"]
    assert row["per_seed"] == [0.5, 0.7, 0.6] and row["min_min_dist"] == 0.5 and row["max_min_dist"] == 0.7
    assert abs(row["mean_min_dist"] - 0.6) < 1e-12 and row["seeds_as_close"] == 2  # 0.6 <= 0.6 counts
    assert "| 2 | 0.6000 [0.5000-0.7000] | 0.6000 | 0.500 | 0.400 | 2/3 | 0.6307 | 40 | 100-102 |" in md


def _worker_facts(parent_only_module: str) -> tuple[str, bool]:
    import multiprocessing as mp
    return mp.get_start_method(), parent_only_module in sys.modules


def test_local_workers_are_fresh_interpreters_not_forks():
    # a forked worker inherits the parent's OpenMP runtime and ran a second, spinning thread beside its job
    # (training.sweep.worker_pool); a spawned one imports only what its job needs
    import colorsys  # noqa: F401  (imported here, in the parent only)
    from training.sweep import worker_pool
    with worker_pool(1) as pool:
        method, inherited = pool.submit(_worker_facts, "colorsys").result(timeout=120)
    assert method == "spawn" and not inherited


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def test_sigterm_stops_the_sweep_queued_jobs_never_start_running_ones_checkpoint(tmp_path):
    # one worker, two long jobs: the first trains, the second is queued
    p = _sweep_file(tmp_path).read_text().replace("steps = 40\n", "steps = 200000\n") \
        .replace("checkpoint_every = 1000", "checkpoint_every = 100000") \
        .replace("imitation_steps = 20", "imitation_steps = 0") \
        .replace("imitation_polish_steps = 20", "imitation_polish_steps = 0")  # no DAgger phase: nothing to polish
    (tmp_path / "sweep.toml").write_text(p)
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from training.cli import main; sys.exit(main())",
                             "sweep", "--config", str(tmp_path / "sweep.toml"), "--workers", "1"],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group: the finally below ends every worker
    first, second = tmp_path / "runs" / "np1_s0", tmp_path / "runs" / "np2_s0"
    try:
        metrics = first / "metrics.csv"
        # generous waits that still end inside pytest-timeout's 300 s, so that a hang reports what it waited for
        assert wait_until(lambda: metrics.is_file() and len(metrics.read_text().splitlines()) >= 2, 120, 0.2), \
            "the first job wrote no metrics row"
        proc.terminate()  # SIGTERM to the sweep alone, as `kill PID` does
        out, err = proc.communicate(timeout=120)
        assert wait_until(lambda: not _group_alive(proc.pid), 30, 0.2), "a process of the sweep outlived it"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the sweep and its workers, whatever happened above
        except ProcessLookupError:
            pass
    assert proc.returncode == 130, err
    assert "interrupted" in err and "1 queued jobs not started" in out
    assert (first / "checkpoints" / "state.pt").is_file()  # the running job saved where it was
    assert not second.exists()  # the queued job never started
