"""``swarm-train sweep``: the pursuer-count sweep (the paper's Table I) as one command.

A sweep file (``configs/sweep.toml``) names a base experiment config, the pursuer counts and the seeds:

```toml
base = "configs/multi_target.toml"   # relative to the sweep file's folder's parent, or absolute
n_pursuers = [2, 3, 4, 5, 6]
seeds = [0]
out = "runs/sweep"                   # one run folder per job: <out>/np<N>_s<S>
eval_episodes = 200                  # held-out episodes per job (0 skips evaluation)
eval_evader = "scripted"             # "learned" or "scripted"
[train]                              # TrainConfig overrides applied to every job (optional)
steps = 4000
threads = 1
```

Every (n_pursuers, seed) job trains (``training.train.train``) and then evaluates its actors on held-out seeds
(``training.learned_eval.evaluate_learned``); the jobs run in parallel as local processes
(``concurrent.futures.ProcessPoolExecutor``) or, with ``--ray ADDRESS``, as Ray tasks on a cluster (``ray`` is
the optional extra ``pip install swarmpursuit[ray]``; ``--ray local`` starts a local Ray instance). The run
folders live on the filesystem the workers see, so a Ray cluster needs a shared filesystem (or run the sweep
from the head node). The summary (``<out>/sweep.json`` and a Markdown table beside the paper's Table I) is
written when every job is done.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import logging
import multiprocessing
import os
import signal
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from runtime.spec import SpecError, load_toml
from training.config import ExperimentConfig, TrainConfig

log = logging.getLogger(__name__)

_SWEEP_KEYS = {"base", "n_pursuers", "seeds", "out", "eval_episodes", "eval_evader", "eval_seed", "train"}


@dataclass(frozen=True)
class SweepConfig:
    base: Path
    n_pursuers: tuple[int, ...] = (2, 3, 4, 5, 6)
    seeds: tuple[int, ...] = (0,)
    out: Path = Path("runs/sweep")
    eval_episodes: int = 200
    eval_evader: str = "scripted"
    eval_seed: int = 0
    train: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_toml(cls, path: str | Path) -> "SweepConfig":
        path = Path(path)
        doc = load_toml(path)
        where = path.name
        unknown = sorted(set(doc) - _SWEEP_KEYS)
        if unknown:
            raise SpecError(f"{where}: unknown key {unknown[0]!r}; known keys: {sorted(_SWEEP_KEYS)}")
        if "base" not in doc:
            raise SpecError(f"{where}: base: missing; name the experiment config to sweep, e.g. "
                            f"base = \"configs/multi_target.toml\"")
        base = Path(doc["base"])
        if not base.is_absolute() and not base.is_file():
            base = path.resolve().parent.parent / base
        if not base.is_file():
            raise SpecError(f"{where}: base: {doc['base']!r} does not exist")

        def int_list(key: str, default: tuple[int, ...], lo: int) -> tuple[int, ...]:
            v = doc.get(key, list(default))
            if not isinstance(v, list) or not v or any(not isinstance(x, int) or isinstance(x, bool) or x < lo
                                                        for x in v):
                raise SpecError(f"{where}: {key}: must be a non-empty list of whole numbers >= {lo}, got {v!r}")
            return tuple(v)

        n_p = int_list("n_pursuers", cls.n_pursuers, 1)
        seeds = int_list("seeds", cls.seeds, 0)
        eps = doc.get("eval_episodes", cls.eval_episodes)
        if not isinstance(eps, int) or eps < 0:
            raise SpecError(f"{where}: eval_episodes: must be a whole number >= 0, got {eps!r}")
        evader = doc.get("eval_evader", cls.eval_evader)
        if evader not in ("learned", "scripted"):
            raise SpecError(f"{where}: eval_evader: {evader!r} is not one of 'learned', 'scripted'")
        train = doc.get("train", {})
        if not isinstance(train, dict):
            raise SpecError(f"{where}: train: must be a table of TrainConfig fields")
        names = {f.name for f in dataclasses.fields(TrainConfig)}
        bad = sorted(set(train) - names)
        if bad:
            raise SpecError(f"{where}: train.{bad[0]}: not a TrainConfig field")
        cfg = cls(base=base, n_pursuers=n_p, seeds=seeds, out=Path(doc.get("out", str(cls.out))),
                  eval_episodes=eps, eval_evader=evader, eval_seed=int(doc.get("eval_seed", 0)), train=train)
        for job in cfg.jobs():  # validate every job's config now, not in a worker
            job_config(cfg, *job)
        return cfg

    def jobs(self) -> list[tuple[int, int]]:
        return [(n, s) for n in self.n_pursuers for s in self.seeds]


def job_config(sweep: SweepConfig, n_pursuers: int, seed: int) -> ExperimentConfig:
    """The base config with ``n_pursuers`` pursuers, the sweep's train overrides and ``seed``."""
    doc = load_toml(sweep.base)
    doc.setdefault("spec", {}).setdefault("team", {})["n_pursuers"] = n_pursuers
    doc["train"] = {**doc.get("train", {}), **sweep.train, "seed": seed}
    doc["name"] = f"{doc.get('name', 'sweep')}_np{n_pursuers}"
    return ExperimentConfig.from_dict(doc, f"{sweep.base.name} (n_pursuers={n_pursuers}, seed={seed})")


def run_job(cfg_dict: dict[str, Any], out: str, eval_episodes: int, eval_evader: str, eval_seed: int,
            resume: bool = False) -> dict[str, Any]:
    """Train one job into ``out`` and evaluate it; returns a JSON-able summary. Runs in a worker process
    (local or Ray), so it takes and returns plain data."""
    from training.learned_eval import evaluate_learned
    from training.train import train

    cfg = ExperimentConfig.from_dict(cfg_dict)
    t0 = time.perf_counter()
    result = train(cfg, out, resume=resume, progress=False)
    res: dict[str, Any] = {"out": out, "n_pursuers": cfg.spec.team.n_pursuers, "seed": cfg.train.seed,
                           "train": result.to_dict()}
    if eval_episodes > 0 and not result.interrupted:
        ev = evaluate_learned(run=out, evader=eval_evader, episodes=eval_episodes, seed=eval_seed, n_envs=50,
                              classical=True, progress=False)
        from runtime.cliutil import write_text_atomic
        write_text_atomic(Path(out, f"eval_{eval_evader}.json"), json.dumps(ev, indent=2, sort_keys=True) + "\n")
        res["eval"] = {k: v for k, v in ev.items() if k != "classical"}
        res["classical"] = ev["classical"]
    res["wall_s"] = round(time.perf_counter() - t0, 2)
    return res


def _job_args(sweep: SweepConfig, n: int, s: int) -> tuple[dict[str, Any], str, int, str, int, bool]:
    out = sweep.out / f"np{n}_s{s}"
    resume = (out / "checkpoints" / "state.pt").is_file()
    return (job_config(sweep, n, s).to_dict(), str(out), sweep.eval_episodes, sweep.eval_evader, sweep.eval_seed,
            resume)


def _log_info(line: str) -> None:
    log.info("%s", line)


def _worker_init() -> None:
    # Ctrl-C reaches the workers too (one process group): a job in training stops with a checkpoint
    # (training.train.install_stop_handlers); between jobs or in an evaluation a worker ignores it and the
    # sweep, which cancelled every queued job, waits for it instead of a worker dying with a traceback
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """The local workers: fresh interpreters (``spawn``), not forks of this process. A job in a forked worker
    carried a second OpenMP thread of torch's libgomp spinning beside it whatever ``train.threads`` said (seen
    with gdb: ``gomp_barrier_wait_end``), and two such jobs on the 2 cores ran at 120 frames/s against 640-760
    in spawned workers, the same job and steps (``configs/sweep_v5.toml``, 2026-12-03)."""
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=_worker_init)


def run_local(sweep: SweepConfig, workers: int, echo: Callable[[str], None] = _log_info) -> list[dict[str, Any]]:
    """Every job of ``sweep`` on ``workers`` local processes; ``echo`` gets one line per finished job.

    Ctrl-C or SIGTERM stops the sweep: no queued job starts, every job in training saves a checkpoint and
    stops (a SIGTERM to this process is passed on to the workers; Ctrl-C in a terminal reaches them itself),
    then ``KeyboardInterrupt`` propagates. Running the sweep again resumes those jobs."""
    from training.train import install_stop_handlers
    results = []
    todo = list(sweep.jobs())
    running: dict[Any, tuple[int, int]] = {}
    pool = worker_pool(workers)
    restore = install_stop_handlers()
    try:
        while todo or running:
            # at most one job per worker handed to the pool: the pool moves what it is given into its call
            # queue at once, beyond the reach of cancel(), so a stop would still start a queued job
            while todo and len(running) < workers:
                n, s = todo.pop(0)
                running[pool.submit(run_job, *_job_args(sweep, n, s))] = (n, s)
            done, _ = wait(running, return_when=FIRST_COMPLETED)
            for fut in done:
                n, s = running.pop(fut)
                res = fut.result()
                echo(f"done: n_pursuers={n} seed={s}: " + _one_line(res))
                results.append(res)
    except KeyboardInterrupt as exc:
        if str(exc) == "SIGTERM":  # sent to this process alone: pass it on to the jobs in training
            for proc in list((pool._processes or {}).values()):
                if proc.is_alive():
                    os.kill(proc.pid, signal.SIGTERM)
        echo(f"interrupted: {len(todo)} queued jobs not started; waiting for the {len(running)} running jobs to "
             f"save their checkpoints")
        raise
    finally:
        restore()
        pool.shutdown(wait=True)
    return results


def run_ray(sweep: SweepConfig, address: str, cpus_per_job: float = 1.0,
            echo: Callable[[str], None] = _log_info) -> list[dict[str, Any]]:
    """Every job of ``sweep`` as a Ray task at ``address`` ("local" starts one); ``echo`` as in ``run_local``."""
    try:
        import ray
    except ImportError:
        raise SpecError("--ray needs Ray: pip install 'swarmpursuit[ray]'") from None
    started = not ray.is_initialized()
    if started:
        if address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=cpus_per_job)(run_job)
        refs = {task.remote(*_job_args(sweep, n, s)): (n, s) for n, s in sweep.jobs()}
        results = []
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            res = ray.get(ready[0])
            n, s = refs[ready[0]]
            echo(f"done: n_pursuers={n} seed={s}: " + _one_line(res))
            results.append(res)
        return results
    finally:
        if started:
            ray.shutdown()


def _one_line(res: dict[str, Any]) -> str:
    t = res["train"]
    s = f"{t['env_steps']} env steps in {t['train_time_s']:.0f} s ({t['fps']:.0f} frames/s)"
    if "eval" in res:
        s += f", min dist {res['eval']['mean_min_dist']:.4f} m (classical {res['classical']['mean_min_dist']:.4f})"
    return s


def summarize_sweep(sweep: SweepConfig, results: list[dict[str, Any]]) -> tuple[dict[str, Any], str]:
    """(the sweep.json document, a Markdown table beside the paper's Table I)."""
    from training.evaluate import PAPER, mean_of
    paper = PAPER["table_i"]
    rows = []
    for n in sweep.n_pursuers:
        mine = [r for r in results if r["n_pursuers"] == n and "eval" in r]
        if not mine:
            continue
        ours, classical = mean_of([r["eval"] for r in mine]), mean_of([r["classical"] for r in mine])
        mins = [r["eval"]["mean_min_dist"] for r in mine]
        cmins = [r["classical"]["mean_min_dist"] for r in mine]
        rows.append({"n_pursuers": n, "seeds": [r["seed"] for r in mine],
                     "mean_min_dist": ours["mean_min_dist"], "per_seed": mins,
                     "min_min_dist": min(mins), "max_min_dist": max(mins),
                     "mean_avg_dist": ours["mean_avg_dist"], "tracking_rate": ours["tracking_rate"],
                     "classical_mean_min_dist": classical["mean_min_dist"],
                     "classical_tracking_rate": classical["tracking_rate"],
                     "seeds_as_close": sum(m <= c for m, c in zip(mins, cmins)),
                     "paper_mean_min_dist": paper.get(n),
                     "train_time_s": [r["train"]["train_time_s"] for r in mine],
                     "env_steps": [r["train"]["env_steps"] for r in mine],
                     "fps": [r["train"]["fps"] for r in mine]})
    doc = {"base": str(sweep.base), "evader": sweep.eval_evader, "eval_episodes": sweep.eval_episodes,
           "eval_seed": sweep.eval_seed, "train_overrides": sweep.train, "rows": rows, "jobs": results}
    md = [f"Table I: mean minimum pursuer-evader distance [m] vs number of pursuers (2 evaders), "
          f"{sweep.eval_episodes} held-out episodes vs {sweep.eval_evader} evaders",
          "(ours: mean [min-max] over the seeds; classical: the classical team on the same evaders and episodes; "
          "seeds: those whose team is as close as the classical team)",
          "", "| n_p | ours | classical | tracking ours | classical | seeds | paper | env steps | train time [s] |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r["paper_mean_min_dist"]
        spread = f" [{r['min_min_dist']:.4f}-{r['max_min_dist']:.4f}]" if len(r["seeds"]) > 1 else ""
        md.append(f"| {r['n_pursuers']} | {r['mean_min_dist']:.4f}{spread} | {r['classical_mean_min_dist']:.4f} | "
                  f"{r['tracking_rate']:.3f} | {r['classical_tracking_rate']:.3f} | "
                  f"{r['seeds_as_close']}/{len(r['seeds'])} | {'' if p is None else f'{p:.4f}'} | "
                  f"{max(r['env_steps'])} | {min(r['train_time_s']):.0f}-{max(r['train_time_s']):.0f} |")
    return doc, "\n".join(md) + "\n"


# ------------------------------------------------------------------------------------------------ CLI


def add_sweep_parser(sub: Any) -> None:
    from runtime.cliutil import out_dir, out_file, positive_int
    p = sub.add_parser(
        "sweep", help="train and evaluate the pursuer-count sweep (Table I) in parallel",
        description="Trains one run per (n_pursuers, seed) of a sweep file and evaluates each on held-out "
                    "seeds; local processes by default, a Ray cluster with --ray ADDRESS. A job whose run "
                    "folder holds a checkpoint is resumed. Ctrl-C or SIGTERM stops a local sweep: no queued "
                    "job starts and every job in training saves a checkpoint first.")
    p.add_argument("--config", default="configs/sweep.toml", metavar="PATH",
                   help="sweep TOML (default configs/sweep.toml)")
    p.add_argument("--steps", type=positive_int, metavar="N", help="env steps per job (overrides the sweep's train.steps)")
    p.add_argument("--out", type=out_dir, metavar="DIR", help="folder of the job runs (overrides the sweep's out)")
    p.add_argument("--workers", type=positive_int, default=2, metavar="K", help="local worker processes (default 2)")
    p.add_argument("--ray", metavar="ADDRESS",
                   help="run the jobs as Ray tasks: a cluster address (ray://host:10001, auto) or 'local'")
    p.add_argument("--json", type=out_file, metavar="PATH", help="also write the summary JSON here (besides <out>/sweep.json)")
    p.set_defaults(func=cmd_sweep)


def cmd_sweep(args: Any) -> int:
    import argparse

    from runtime.cliutil import check_out_dir, check_out_file, write_text_atomic
    from training.cli import UsageError
    sweep = SweepConfig.from_toml(args.config)
    if args.steps is not None:
        if args.steps < 1:
            raise UsageError(f"--steps: must be >= 1, got {args.steps}")
        sweep = dataclasses.replace(sweep, train={**sweep.train, "steps": args.steps})
    if args.out:
        sweep = dataclasses.replace(sweep, out=Path(args.out))
    if args.workers < 1:
        raise UsageError(f"--workers: must be >= 1, got {args.workers}")
    try:  # the sweep file's out too, before hours of training
        check_out_dir(sweep.out)
        if args.json:
            check_out_file(Path(args.json).with_suffix(".md"))
    except argparse.ArgumentTypeError as exc:
        raise UsageError(f"out: {exc}") from None
    for job in sweep.jobs():
        job_config(sweep, *job)
    t0 = time.perf_counter()
    print(f"sweep: {len(sweep.jobs())} jobs (n_pursuers {list(sweep.n_pursuers)} x seeds {list(sweep.seeds)}) "
          f"into {sweep.out}, " + (f"on Ray at {args.ray}" if args.ray else f"{args.workers} local workers"),
          flush=True)
    echo = functools.partial(print, flush=True)  # one line per finished job, to the user
    results = run_ray(sweep, args.ray, echo=echo) if args.ray else run_local(sweep, args.workers, echo=echo)
    doc, md = summarize_sweep(sweep, results)
    doc["wall_s"] = round(time.perf_counter() - t0, 2)
    write_text_atomic(sweep.out / "sweep.json", json.dumps(doc, indent=2, sort_keys=True) + "\n")
    write_text_atomic(sweep.out / "sweep.md", md)
    if args.json:
        write_text_atomic(args.json, json.dumps(doc, indent=2, sort_keys=True) + "\n")
        write_text_atomic(Path(args.json).with_suffix(".md"), md)
    print(md)
    print(f"wrote {sweep.out / 'sweep.json'}" + (f" and {args.json}" if args.json else ""))
    return 0
