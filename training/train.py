"""The training loop: many envs stepped together, batched MADDPG updates, logs, checkpoints, resume.

A run folder holds:

- ``config.toml``: the resolved experiment config (every field, with command-line overrides applied);
- ``run.json``: git revision, command line, start times; ``summary.json``: counts and speeds at the end;
- ``metrics.csv``: one row every ``train.log_every`` env steps, columns ``CSV_COLUMNS`` (rewards are the
  env's, unscaled, averaged per agent of the role over the window; ``return_*`` are mean episode returns of
  episodes finished in the window; distances are pursuer-evader centre distances [m] as in runtime.metrics);
- ``tb/``: the same scalars as TensorBoard events;
- ``checkpoints/state.pt`` (+ ``buffer.pt``): the full training state for ``--resume``, written all or nothing (a
  full disk leaves the previous checkpoint whole: ``training.checkpoint.save_torch_files``);
- ``actors.pt``: the per-agent actors in the ``training.checkpoint`` format (what export and evaluation read),
  rewritten with every checkpoint.

Episodes in flight when a run is interrupted are not saved; a resumed run starts fresh episodes.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from runtime.avoidance import avoid_agents
from runtime.cliutil import write_text_atomic
from runtime.observation import encode_observations
from runtime.spec import Role
from training.checkpoint import save_actors, save_torch_files
from training.config import ExperimentConfig, TrainConfig
from training.env import PursuitEnv
from training.maddpg import CloneBuffer, ReplayBuffer
from training.opponents import OpponentMixer
from training.rolecritic import make_learner

log = logging.getLogger(__name__)

ROLES = ("pursuer", "scout", "evader")
CSV_COLUMNS = ("step", "frames", "updates", "time_s", "fps", "updates_per_s", "noise_std",
               *(f"reward_{r}" for r in ROLES), *(f"return_{r}" for r in ROLES),
               "min_dist", "avg_dist", "max_dist", "captures_per_step", "episodes",
               "critic_loss", "actor_loss", "q_mean", "int8_sensitivity", "imitation_mse", "teacher_share")
STATE_FORMAT = 1


def teacher_pursuers(tc: TrainConfig) -> Any:
    """The DAgger teacher's pursuer team for ``train.teacher = "classical"``: ``ClassicalPursuers`` with ``tc``'s
    ``teacher_*`` options (the classical team itself with every one of them at its default)."""
    from training.baselines import ClassicalPursuers
    pursuers = ClassicalPursuers()
    pursuers.separation_gain = tc.teacher_separation_gain
    pursuers.assignment = tc.teacher_assignment
    pursuers.obstacle_side_softness = tc.teacher_obstacle_softness
    pursuers.lead_time_max = tc.teacher_lead_time
    if tc.teacher_lead_others != tc.teacher_lead_time:
        pursuers.lead_time_others = tc.teacher_lead_others
    pursuers.lead_side_time, pursuers.lead_side_angle = tc.teacher_side_lead, tc.teacher_side_angle
    pursuers.lead_side_wall = tc.teacher_side_wall
    pursuers.scout_sweep, pursuers.scout_sweep_mode = tc.teacher_scout_sweep, tc.teacher_scout_sweep_mode
    pursuers.scout_sweep_clear = tc.teacher_scout_sweep_clear
    return pursuers


def full_speed_labels(actions: np.ndarray, full: float = 0.999) -> np.ndarray:
    """The teacher's actions ``[..., 2]`` as the students learn them: clipped to [-1, 1], and every action that asks
    for full speed (norm >= ``full``) stretched along its direction until one axis reaches 1. The world limits an
    action's norm to 1 (``runtime.world.action_to_velocity``), so both mean the same velocity; but a regression
    toward a unit vector lands inside the circle about as often as outside, and inside is slower: cloned from
    unit vectors, the pursuers flew at 0.70 m/s on average where the classical team flies at 0.81 m/s (role_based
    against the wanderer). Stretched, the clone's error falls beyond the limit, where it costs no speed."""
    a = np.clip(actions, -1.0, 1.0)
    norm = np.sqrt((a * a).sum(-1, keepdims=True))
    top = np.abs(a).max(-1, keepdims=True)
    return np.where(norm >= full, a / np.maximum(top, 1e-12), a)


class RunError(RuntimeError):
    """A run folder cannot be used as asked (missing checkpoint, mismatching config)."""


@dataclass
class TrainResult:
    out: Path
    env_steps: int
    frames: int
    updates: int
    train_time_s: float
    interrupted: bool

    @property
    def fps(self) -> float:
        return self.frames / max(self.train_time_s, 1e-9)

    @property
    def updates_per_s(self) -> float:
        return self.updates / max(self.train_time_s, 1e-9)

    def to_dict(self) -> dict[str, Any]:
        return {"env_steps": self.env_steps, "frames": self.frames, "updates": self.updates,
                "train_time_s": round(self.train_time_s, 3), "fps": round(self.fps, 2),
                "updates_per_s": round(self.updates_per_s, 3), "interrupted": self.interrupted}


# ------------------------------------------------------------------------------------------- helpers


def git_revision(cwd: Path | None = None) -> str:
    """``<sha>`` or ``<sha>-dirty`` of the source tree, ``unknown`` outside a git checkout."""
    where = cwd or Path(__file__).resolve().parent.parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True,
                             timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=where,
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("-dirty" if dirty else "")


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write non-finite {v!r} to TOML")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: dict[str, Any], prefix: str = "") -> str:
    """A nested dict of scalars and lists as TOML (what ``ExperimentConfig.to_dict`` gives). A None value is left out:
    TOML has no null, and a key left out loads as its default, which for every optional setting is None."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict) and v is not None]
    for k, v in doc.items():
        if isinstance(v, dict):
            name = f"{prefix}.{k}" if prefix else k
            if any(not isinstance(x, dict) for x in v.values()):
                lines += ["", f"[{name}]"]
            lines.append(dump_toml(v, name).rstrip("\n"))
    return "\n".join(x for x in lines if x is not None).strip() + "\n"


class _Window:
    """Sums of the logged quantities since the last CSV row."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.n = 0
        self.reward = {r: 0.0 for r in ROLES}
        self.dist = np.zeros(3)
        self.captures = 0.0
        self.returns: dict[str, list[float]] = {r: [] for r in ROLES}
        self.losses: dict[str, float] = {}
        self.n_updates = 0
        self.clone_mse = 0.0
        self.n_clone = 0


# ---------------------------------------------------------------------------------------------- loop


@dataclass(frozen=True)
class _EnvView:
    """What a scripted policy reads of an env (``spec``, ``state``), for states the env is not in."""

    spec: Any
    state: Any


class Trainer:
    """Owns the env, the learner, the buffer and the run folder of one training run."""

    def __init__(self, cfg: ExperimentConfig, out: str | Path, resume: bool = False,
                 init_from: str | Path | None = None) -> None:
        self.cfg = cfg
        self.tc = tc = cfg.train
        self.out = Path(out)
        torch.set_num_threads(tc.threads)
        _set_numba_threads(tc.threads)
        if tc.device.startswith("cuda") and not torch.cuda.is_available():
            raise RunError(f"train.device = {tc.device!r} but torch sees no CUDA device: use --device cpu")
        self.spec = cfg.spec
        self.env = PursuitEnv(cfg.spec, cfg.rewards, n_envs=tc.n_envs, seed=tc.seed)
        self.agent = make_learner(cfg.spec, tc)
        self.np_rng = np.random.default_rng(tc.seed + 3)
        self.mixer = OpponentMixer(cfg.spec, tc, np.random.default_rng(tc.seed + 4))
        self.teacher = None
        if tc.teacher == "classical":  # the classical team (true state): pursuit + Lloyd scouting, fleeing evaders
            from training.baselines import FleeingEvaders, TeamPolicy
            self.teacher = TeamPolicy(teacher_pursuers(tc), FleeingEvaders())
        self.teacher_rng = np.random.default_rng(tc.seed + 5)
        # the polish's own sample stream, so that the run's others are those of a run without it
        self.polish_gen = torch.Generator(device=tc.device).manual_seed(tc.seed + 6)
        self._learns = self.agent.learn_mask.cpu().numpy() > 0  # [N] agents whose actors train
        self.buffer = ReplayBuffer(tc.buffer_size, cfg.spec.n_agents, cfg.spec.max_obs_dim, 2, tc.device)
        self.sample_gen = torch.Generator(device=tc.device).manual_seed(tc.seed + 1)
        # train.imitation_augment: its rows, their draws and their own sample stream (a run without it draws as before)
        self.clone_buffer = None
        if tc.imitation_augment:
            self.clone_buffer = CloneBuffer(min(tc.buffer_size, tc.imitation_steps * tc.n_envs), cfg.spec.n_agents,
                                            cfg.spec.max_obs_dim, 2, tc.device)
        self.augment_rng = np.random.default_rng(tc.seed + 7)
        self.augment_gen = torch.Generator(device=tc.device).manual_seed(tc.seed + 8)
        self.noise_gen = torch.Generator(device=tc.device).manual_seed(tc.seed + 2)
        self.env_step = 0
        self.polished = 0  # cloning steps done of train.imitation_polish_steps
        self.elapsed = 0.0  # training wall time of previous sessions [s]
        team = cfg.spec.team
        self.role_idx = {r.label: np.asarray(team.indices(r)) for r in Role if len(team.indices(r))}
        self.pursuers = (np.asarray(team.indices(Role.PURSUER)) if team.n_pursuers
                         else np.asarray(team.indices(Role.SCOUT)))
        self.returns = np.zeros((tc.n_envs, cfg.spec.n_agents))
        self.ckpt_dir = self.out / "checkpoints"
        if resume and init_from is not None:
            raise RunError("--resume and --init-from exclude each other: resume continues a run in place, "
                           "--init-from starts a new run from another run's checkpoint")
        if resume:
            self._load_checkpoint()
        else:
            self._init_run_folder()
            if init_from is not None:
                self._init_from(Path(init_from))

    # -- run folder ---------------------------------------------------------------------------------
    def _init_run_folder(self) -> None:
        if (self.ckpt_dir / "state.pt").exists():
            raise RunError(f"{self.out} already holds a run: pass --resume to continue it, or choose another --out")
        self.out.mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.out / "config.toml", dump_toml(self.cfg.to_dict()))
        run = {"git_revision": git_revision(), "command": sys.argv, "started_utc": _utc_now(),
               "spec_hash": self.spec.hash, "torch": torch.__version__}
        write_text_atomic(self.out / "run.json", json.dumps(run, indent=2) + "\n")
        with (self.out / "metrics.csv").open("w", newline="") as fh:
            csv.writer(fh).writerow(CSV_COLUMNS)

    def _restore(self, ckpt_dir: Path, what: str) -> None:
        """Networks, optimizers, step counter, random streams and replay buffer from ``ckpt_dir``."""
        path = ckpt_dir / "state.pt"
        if not path.is_file():
            raise RunError(f"nothing to {what} in {ckpt_dir.parent}: {path} does not exist")
        st = torch.load(path, map_location=self.tc.device, weights_only=False)
        if st.get("format") != STATE_FORMAT:
            raise RunError(f"{path} has training-state format {st.get('format')}, this code reads {STATE_FORMAT}")
        if st["spec_hash"] != self.spec.hash:
            raise RunError(f"{path} was trained with spec {st['spec_hash']}, the config gives {self.spec.hash}: "
                           f"{what} with a config of the same spec (the run's own config.toml)")
        self.agent.load_state_dict(st["agent"])
        self.env_step = int(st["env_step"])
        self.elapsed = float(st["elapsed"])
        self.sample_gen.set_state(st["sample_gen"].cpu() if self.tc.device == "cpu" else st["sample_gen"])
        self.noise_gen.set_state(st["noise_gen"].cpu() if self.tc.device == "cpu" else st["noise_gen"])
        self.np_rng.bit_generator.state = st["np_rng"]
        self.env.world.rng.bit_generator.state = st["world_rng"]
        if "teacher_rng" in st:
            self.teacher_rng.bit_generator.state = st["teacher_rng"]
        self.polished = int(st.get("polished", 0))  # absent in checkpoints written before the polish
        if "polish_gen" in st:
            self.polish_gen.set_state(st["polish_gen"].cpu() if self.tc.device == "cpu" else st["polish_gen"])
        if "augment_rng" in st:
            self.augment_rng.bit_generator.state = st["augment_rng"]
            self.augment_gen.set_state(st["augment_gen"].cpu() if self.tc.device == "cpu" else st["augment_gen"])
        cpath = ckpt_dir / "clone_buffer.pt"
        if self.clone_buffer is not None and cpath.is_file():
            self.clone_buffer.load_state_dict(torch.load(cpath, map_location=self.tc.device, weights_only=True))
        if "opponents" in st:
            self.mixer.load_state_dict(st["opponents"], self.agent.frozen_actors())
            self.mixer.rng.bit_generator.state = st["opponent_rng"]
        bpath = ckpt_dir / "buffer.pt"
        if bpath.is_file():
            self.buffer.load_state_dict(torch.load(bpath, map_location=self.tc.device, weights_only=True))
        else:
            log.warning("no replay buffer saved in %s: refilling it from scratch", ckpt_dir)

    def _init_from(self, src: Path) -> None:
        """Start this (new) run from ``src``'s last checkpoint: a fine-tune under this run's config."""
        self._restore(src / "checkpoints", "start from")
        if self.env_step >= self.tc.steps and not self.tc.es_iterations:
            raise RunError(f"{src} is already at env step {self.env_step}: set train.steps (or --steps) above it "
                           f"to fine-tune, or train.es_iterations for evolution strategies alone")
        run = json.loads((self.out / "run.json").read_text())
        run["init_from"] = {"run": str(src), "at_step": self.env_step}
        write_text_atomic(self.out / "run.json", json.dumps(run, indent=2) + "\n")
        log.info("started %s from %s at env step %d (%d updates, %d transitions in the buffer)", self.out, src,
                 self.env_step, self.agent.updates, len(self.buffer))

    def _load_checkpoint(self) -> None:
        self._restore(self.ckpt_dir, "resume")
        self._truncate_csv(self.env_step)
        run = json.loads((self.out / "run.json").read_text()) if (self.out / "run.json").is_file() else {}
        run.setdefault("resumed", []).append({"at_step": self.env_step, "utc": _utc_now(),
                                              "git_revision": git_revision(), "command": sys.argv})
        write_text_atomic(self.out / "run.json", json.dumps(run, indent=2) + "\n")
        log.info("resumed %s at env step %d (%d updates, %d transitions in the buffer)", self.out, self.env_step,
                 self.agent.updates, len(self.buffer))

    def _truncate_csv(self, step: int) -> None:
        path = self.out / "metrics.csv"
        rows: list[list[str]] = []
        if path.is_file():
            with path.open(newline="") as fh:
                rows = list(csv.reader(fh))
        keep = [CSV_COLUMNS] + [r for r in rows[1:] if r and int(r[0]) <= step]
        with path.open("w", newline="") as fh:
            csv.writer(fh).writerows(keep)

    def save_checkpoint(self) -> None:
        self.ckpt_dir.mkdir(parents=True, exist_ok=True)
        st = {"format": STATE_FORMAT, "spec_hash": self.spec.hash, "agent": self.agent.state_dict(),
              "env_step": self.env_step, "elapsed": self.elapsed + self._session_time(),
              "sample_gen": self.sample_gen.get_state(), "noise_gen": self.noise_gen.get_state(),
              "np_rng": self.np_rng.bit_generator.state, "world_rng": self.env.world.rng.bit_generator.state,
              "config": self.cfg.to_dict(), "opponents": self.mixer.state_dict(),
              "opponent_rng": self.mixer.rng.bit_generator.state, "teacher_rng": self.teacher_rng.bit_generator.state,
              "polished": self.polished, "polish_gen": self.polish_gen.get_state(),
              "augment_rng": self.augment_rng.bit_generator.state, "augment_gen": self.augment_gen.get_state()}
        files: list[tuple[Any, Path]] = []
        if self.tc.checkpoint_buffer:
            files.append((self.buffer.state_dict(), self.ckpt_dir / "buffer.pt"))
            if self.clone_buffer is not None:
                files.append((self.clone_buffer.state_dict(), self.ckpt_dir / "clone_buffer.pt"))
        files.append((st, self.ckpt_dir / "state.pt"))
        # all or nothing: a full disk keeps the previous checkpoint whole (state and buffer of the same step)
        save_torch_files(files, "free some space" + (" (or set train.checkpoint_buffer = false: the replay buffer is "
                                                      "most of a checkpoint)" if self.tc.checkpoint_buffer else "")
                         + ", then continue the run with --resume")
        meta = {"git_revision": git_revision(), "env_steps": self.env_step, "updates": self.agent.updates,
                "run": str(self.out)}
        save_actors(self.out / "actors.pt", self.spec, self.agent.to_actors(), self.cfg.to_dict(), meta)
        if self.tc.snapshot_actors:
            (self.out / "snapshots").mkdir(exist_ok=True)
            save_actors(self.out / "snapshots" / f"actors_{self.env_step:06d}.pt", self.spec, self.agent.to_actors(),
                        self.cfg.to_dict(), meta)
        log.info("checkpoint at env step %d", self.env_step)

    # -- the loop -----------------------------------------------------------------------------------
    def _session_time(self) -> float:
        return time.perf_counter() - self._t0 if hasattr(self, "_t0") else 0.0

    def noise_std(self) -> float:
        tc = self.tc
        frac = min(1.0, self.env_step / tc.noise_decay_steps)
        return tc.noise_std + frac * (tc.noise_std_final - tc.noise_std)

    def imitating(self) -> bool:
        """Whether this env step is in the imitation (DAgger) phase (``train.imitation_steps``)."""
        return self.env_step < self.tc.imitation_steps

    def imitation_weight(self) -> float:
        """TD3+BC's weight w at this env step: ``train.imitation_weight``, decaying linearly to 0 over
        ``train.imitation_decay_steps`` after the imitation phase when that is set."""
        tc = self.tc
        if not tc.imitation_decay_steps:
            return tc.imitation_weight
        frac = (self.env_step - tc.imitation_steps) / tc.imitation_decay_steps
        return tc.imitation_weight * min(1.0, max(0.0, 1.0 - frac))

    def teacher_share(self) -> float:
        """DAgger's beta: the probability that an env acts with the teacher at this env step."""
        if not self.imitating():
            return 0.0
        return 1.0 - self.env_step / self.tc.imitation_steps

    def _actions(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Actions ``[B, N, 2]`` for every env, ``given`` ``[B, N]``: True where the action is not a learner's
        (scripted or frozen evaders, static agents), so that the TD target bootstraps on it, and the teacher's
        actions ``[B, N, 2]`` (None without ``train.teacher``)."""
        tc = self.tc
        learns = self._learns
        teach = None
        if self.teacher is not None and (self.imitating() or tc.imitation_weight > 0):  # else nobody reads it
            teach = full_speed_labels(np.asarray(self.teacher.act(obs, self.env), dtype=np.float64))
        if self.imitating():  # DAgger: the teacher flies a share beta of the envs, the learners the rest
            if self.clone_buffer is not None:
                self._augment()
            a = self.agent.act(obs, self.noise_std(), self.noise_gen).cpu().numpy().astype(np.float64)
            by_teacher = self.teacher_rng.random(tc.n_envs) < self.teacher_share()
            rows = by_teacher[:, None] & learns[None, :]
            a[rows] = teach[rows]
        elif self.env_step < tc.warmup_steps:
            a = self.np_rng.uniform(-1.0, 1.0, (tc.n_envs, self.spec.n_agents, 2))
            a = a * learns[None, :, None]
        else:
            a = self.agent.act(obs, self.noise_std(), self.noise_gen).cpu().numpy().astype(np.float64)
        given = np.broadcast_to(~learns, a.shape[:2]).copy()
        if self.mixer.active:
            given |= self.mixer.apply(obs, a, self.env, self.agent.device)
        return a, given, teach

    def _augment(self) -> None:
        """``train.imitation_augment``: this step's states with every evader's velocity redrawn (uniform heading,
        speed uniform up to the evader's top speed), observed as the env would and labelled by the teacher, into
        the clone buffer. The env itself is not touched."""
        spec, s, env = self.spec, self.env.state, self.env
        nt = spec.team.n_team
        b, e = s.pos.shape[0], spec.team.n_evaders
        heading = self.augment_rng.uniform(0.0, 2.0 * np.pi, (b, e))
        speed = self.augment_rng.uniform(0.0, 1.0, (b, e)) * spec.evader.max_speed
        vel = s.vel.copy()
        vel[:, nt:] = np.stack([np.cos(heading), np.sin(heading)], -1) * speed[..., None]
        # every sighting made this period (own or relayed) holds the evader's velocity now: the redrawn one
        t = env.time_s()
        know = env.knowledge.copy()
        fresh = know[..., 4] == t[:, None, None]  # [B, n_team, E]
        know[..., 2:4] = np.where(fresh[..., None], vel[:, None, nt:], know[..., 2:4])
        obs = encode_observations(spec, s.pos, vel, s.obstacle_pos, s.obstacle_radius, know, t)
        view = _EnvView(spec, dataclasses.replace(s, vel=vel))
        self.clone_buffer.add(obs, full_speed_labels(np.asarray(self.teacher.act(obs, view), dtype=np.float64)))

    def _clone_sample(self, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """One cloning batch of ``train.imitation_batch`` rows (observations, teacher's actions): from the replay
        buffer (with ``gen``), and a share ``train.imitation_augment`` of it from the clone buffer."""
        tc = self.tc
        k = round(tc.imitation_augment * tc.imitation_batch) if self.clone_buffer is not None \
            and len(self.clone_buffer) else 0
        o, t = self.buffer.sample_fields(tc.imitation_batch - k, gen, ("obs", "teach"))
        if not k:
            return o, t
        ao, at = self.clone_buffer.sample_fields(k, self.augment_gen, ("obs", "teach"))
        return torch.cat([o, ao]), torch.cat([t, at])

    def _executed(self, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """What the world flies: ``actions`` through the spec's avoidance layer (``runtime.avoidance``) for every
        agent acting through a trained actor (learners, frozen snapshots, the DAgger teacher's rows: the layer
        is part of the environment the actors learn in), scripted evaders' actions as they are. The replay
        buffer keeps ``actions``, the actors' own outputs."""
        if not self.spec.avoidance.enabled:
            return actions
        out = avoid_agents(self.spec, obs, actions.copy())
        scripted = self.mixer.scripted_rows()
        out[scripted] = actions[scripted]
        return out

    def _store(self, pending: tuple, actions: np.ndarray | None, given: np.ndarray | None) -> None:
        """Store the previous step's transitions with the next actions now known: the actions really taken
        where they are given (NaN elsewhere: the learners' target actors decide). Envs whose episode ended
        bootstrap on the last given action (the next one was never taken; scripted evaders move smoothly)."""
        obs, act, rew, next_obs, act_given, done_ids, teach = pending
        if actions is None:
            actions, given = act, act_given
        next_act = np.where(given[..., None], actions, np.nan)
        if done_ids is not None:
            next_act[done_ids] = np.where(act_given[done_ids, :, None], act[done_ids], np.nan)
        self.buffer.add(obs, act, rew, next_obs, next_act, teach)

    def run(self, progress: bool = True) -> TrainResult:
        tc = self.tc
        from torch.utils.tensorboard import SummaryWriter
        writer = SummaryWriter(str(self.out / "tb"), purge_step=self.env_step or None)
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=tc.steps, initial=self.env_step, unit="step", dynamic_ncols=True, mininterval=1.0)
        win = _Window()
        self._t0 = time.perf_counter()
        start_step, start_updates = self.env_step, self.agent.updates
        last_t, last_step, last_updates = self._t0, self.env_step, self.agent.updates
        obs = self.env.reset()
        self.mixer.reset(np.arange(tc.n_envs))
        self.returns[:] = 0.0
        interrupted = False
        restore = install_stop_handlers()
        pending = None  # the last step's transitions, stored once the next actions are known
        try:
            if self.env_step < tc.steps and self._polish(progress) and self.env_step == tc.imitation_steps:
                self._save_imitation()  # a run resumed (or started from another) where its polish was due
            while self.env_step < tc.steps:
                actions, given, teach = self._actions(obs)
                if pending is not None:
                    self._store(pending, actions, given)
                    pending = None
                next_obs, rew, done, info = self.env.step(self._executed(obs, actions))
                store_next, done_ids = next_obs, None
                if done.any():
                    done_ids = info["final_env_ids"]
                    store_next = next_obs.copy()
                    store_next[done_ids] = info["final_obs"]
                    self.mixer.reset(done_ids)
                pending = (obs, actions, rew, store_next, given, done_ids, teach)
                obs = next_obs
                self.env_step += 1
                if self.mixer.snapshot_due(self.env_step):  # one actor row per agent, on raw obs
                    self.mixer.add_snapshot(self.agent.frozen_actors())
                self._record(win, rew, done, info)
                if self.env_step == tc.imitation_steps < tc.steps and not tc.imitation_polish_steps:
                    self._save_imitation()  # the cloned team, before RL takes over
                imitation = self.imitating()
                if ((self.env_step >= tc.warmup_steps or imitation) and len(self.buffer) >= tc.batch_size
                        and self.env_step % tc.update_every == 0):
                    for _ in range(tc.updates_per_round):
                        losses = self.agent.update(self.buffer.sample(tc.batch_size, self.sample_gen),
                                                   imitation=imitation, imitation_weight=self.imitation_weight())
                        for k, v in losses.items():
                            win.losses[k] = win.losses.get(k, 0.0) + v
                        win.n_updates += 1
                    if imitation and tc.imitation_updates and len(self.buffer) >= tc.imitation_batch:
                        for _ in range(tc.imitation_updates):
                            o, t = self._clone_sample(self.sample_gen)
                            win.clone_mse += self.agent.clone_step(o, t)
                            win.n_clone += 1
                if tc.imitation_polish_steps and self.env_step == tc.imitation_steps < tc.steps:
                    self._polish(progress)  # after this step's updates, before RL takes over
                    self._save_imitation()
                if bar is not None:
                    bar.update(1)
                if self.env_step % tc.log_every == 0 or self.env_step == tc.steps:
                    now = time.perf_counter()
                    dt = max(now - last_t, 1e-9)
                    row = self._log_row(win, (self.env_step - last_step) * tc.n_envs / dt,
                                        (self.agent.updates - last_updates) / dt, writer)
                    last_t, last_step, last_updates = now, self.env_step, self.agent.updates
                    if bar is not None:
                        bar.set_postfix_str(_postfix(row), refresh=False)
                    win.reset()
                if self.env_step % tc.checkpoint_every == 0 and self.env_step < tc.steps:
                    self.save_checkpoint()
            if self._polish_due():  # the imitation phase ends the run: the polish clones from all of it
                if pending is not None:
                    self._store(pending, None, None)
                    pending = None
                self._polish(progress)
        except KeyboardInterrupt:
            interrupted = True
            log.warning("interrupted at env step %d: saving a checkpoint (continue with --resume)", self.env_step)
        finally:
            restore()
            if pending is not None:  # the run ends here: its last step's next actions are the last given ones
                self._store(pending, None, None)
            if bar is not None:
                bar.close()
        self.save_checkpoint()
        writer.close()
        es_iterations = 0
        if not interrupted and tc.es_iterations and self.env_step >= tc.steps:
            es_iterations, interrupted = self._run_es(progress)
        session = self._session_time()
        result = TrainResult(self.out, self.env_step, (self.env_step - start_step) * tc.n_envs,
                             self.agent.updates - start_updates, session, interrupted)
        summary = {**result.to_dict(), "es_iterations": es_iterations, "polish_steps": self.polished,
                   "total_env_steps": self.env_step, "total_frames": self.env_step * tc.n_envs,
                   "total_updates": self.agent.updates, "total_train_time_s": round(self.elapsed + session, 3),
                   "torch_threads": torch.get_num_threads(), "device": tc.device, "finished_utc": _utc_now()}
        write_text_atomic(self.out / "summary.json", json.dumps(summary, indent=2) + "\n")
        return result

    def _save_imitation(self) -> None:
        save_actors(self.out / "actors_imitation.pt", self.spec, self.agent.to_actors(), self.cfg.to_dict(),
                    {"git_revision": git_revision(), "env_steps": self.env_step, "updates": self.agent.updates,
                     "run": str(self.out), "phase": "imitation"})

    def _polish_due(self) -> bool:
        tc = self.tc
        return bool(tc.imitation_polish_steps) and self.env_step >= tc.imitation_steps \
            and self.polished < tc.imitation_polish_steps

    def _polish(self, progress: bool) -> bool:
        """``train.imitation_polish_steps`` cloning steps of the team's actors on the replay buffer once the imitation
        phase is over (at the end of the env step that ends it, after its updates; where it ends the run, after its
        last transitions are stored; none before it, nor once done), from their own sample stream. The evaders'
        actors and Adam's moments for them are kept as they were (``MADDPG.kept_rows``). Returns whether it cloned.
        An interruption keeps the steps done so far; ``--resume`` does the rest (and with the polish on,
        ``actors_imitation.pt`` is saved after it)."""
        tc = self.tc
        if not self._polish_due():
            return False
        if len(self.buffer) == 0:
            raise RunError("train.imitation_polish_steps: the replay buffer is empty (a run started from a "
                           "checkpoint saved without it, train.checkpoint_buffer = false): nothing to clone from")
        nt = self.spec.team.n_team
        team = torch.zeros(self.spec.n_agents, device=self.agent.device)
        team[:nt] = 1.0
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=tc.imitation_polish_steps, initial=self.polished, unit="step", desc="polish",
                       dynamic_ncols=True, mininterval=1.0)
        t0, first, mse, n = time.perf_counter(), self.polished, 0.0, 0
        try:
            with self.agent.kept_rows(range(nt, self.spec.n_agents)):
                while self.polished < tc.imitation_polish_steps:
                    g0, a0 = self.polish_gen.get_state(), self.augment_gen.get_state()
                    try:
                        o, t = self._clone_sample(self.polish_gen)
                        mse += self.agent.clone_step(o, t, team)
                    except KeyboardInterrupt:  # this step is not counted: --resume draws its sample again
                        self.polish_gen.set_state(g0)
                        self.augment_gen.set_state(a0)
                        raise
                    n += 1
                    self.polished += 1
                    if bar is not None:
                        bar.update(1)
                    if self.polished % 1000 == 0 or self.polished == tc.imitation_polish_steps:
                        log.info("polish: %d/%d cloning steps, the team's clone error %.5f (last %d steps)",
                                 self.polished, tc.imitation_polish_steps, mse / max(n, 1), n)
                        if bar is not None:
                            bar.set_postfix_str(f"mse={mse / max(n, 1):.4f}", refresh=False)
                        mse, n = 0.0, 0
        finally:
            if bar is not None:
                bar.close()
        log.info("polish: %d cloning steps in %.1f s", self.polished - first, time.perf_counter() - t0)
        return True

    # -- evolution strategies after the MADDPG steps (train.es_iterations) ---------------------------
    def _run_es(self, progress: bool) -> tuple[int, bool]:
        """The ES phase (``training.es``), resumable from ``checkpoints/es.pt``: every ``es_checkpoint_every``
        iterations (and on Ctrl-C) the ES state and ``actors.pt`` (team from ES, evaders from the learner) are
        saved; ``es.csv`` has a row per iteration. Returns (iterations done now, interrupted)."""
        from training.es import ES_COLUMNS, TeamES, es_row
        tc = self.tc
        actors = self.agent.to_actors()
        es = TeamES(self.spec, self.cfg.rewards, actors, tc, seed=tc.seed + 13)
        path = self.ckpt_dir / "es.pt"
        if path.is_file():
            es.load_state_dict(torch.load(path, map_location="cpu", weights_only=False))
        start = es.iteration
        csv_path = self.out / "es.csv"
        if es.iteration == 0 or not csv_path.is_file():
            with csv_path.open("w", newline="") as fh:
                csv.writer(fh).writerow(ES_COLUMNS)
        bar = None
        if progress and es.iteration < tc.es_iterations:
            from tqdm import tqdm
            bar = tqdm(total=tc.es_iterations, initial=es.iteration, unit="it", desc="ES", dynamic_ncols=True)

        def save() -> None:
            save_torch_files([(es.state_dict(), path)])
            team = es.team_actors()
            final = [team.get(i, a) for i, a in enumerate(actors)]
            meta = {"git_revision": git_revision(), "env_steps": self.env_step, "updates": self.agent.updates,
                    "es_iterations": es.iteration, "run": str(self.out)}
            save_actors(self.out / "actors.pt", self.spec, final, self.cfg.to_dict(), meta)
            if tc.snapshot_actors:
                (self.out / "snapshots").mkdir(exist_ok=True)
                save_actors(self.out / "snapshots" / f"actors_es{es.iteration:04d}.pt", self.spec, final,
                            self.cfg.to_dict(), meta)

        restore = install_stop_handlers()
        t0 = time.perf_counter()
        interrupted = False
        try:
            while es.iteration < tc.es_iterations:
                row = es.step()
                row["time_s"] = round(time.perf_counter() - t0, 2)
                with csv_path.open("a", newline="") as fh:
                    csv.writer(fh).writerow(es_row(row))
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix_str(f"F={row['fitness']:.3f} dmin={row['min_dist']:.3f} "
                                        f"trk={row['tracking']:.3f}", refresh=False)
                if es.iteration % tc.es_checkpoint_every == 0 or es.iteration == tc.es_iterations:
                    save()
        except KeyboardInterrupt:
            interrupted = True
            log.warning("interrupted at ES iteration %d: saving (continue with --resume)", es.iteration)
            save()
        finally:
            restore()
            if bar is not None:
                bar.close()
        log.info("ES: %d iterations in %.1f s", es.iteration - start, time.perf_counter() - t0)
        return es.iteration - start, interrupted

    def _record(self, win: _Window, rew: np.ndarray, done: np.ndarray, info: dict) -> None:
        win.n += 1
        for r, idx in self.role_idx.items():
            win.reward[r] += float(rew[:, idx].mean())
        nt = self.spec.team.n_team
        d = self.env.world.last_distances[:, self.pursuers][:, :, nt:].reshape(self.tc.n_envs, -1)
        win.dist += (d.min(1).mean(), d.mean(), d.max(1).mean())
        win.captures += float(info["contacts"][:, :nt, nt:].sum()) / self.tc.n_envs
        self.returns += rew
        if done.any():
            ids = info["final_env_ids"]
            for r, idx in self.role_idx.items():
                win.returns[r] += list(self.returns[ids][:, idx].mean(1))
            self.returns[ids] = 0.0

    def _log_row(self, win: _Window, fps: float, ups: float, writer: Any) -> dict[str, Any]:
        n = max(win.n, 1)
        row: dict[str, Any] = {"step": self.env_step, "frames": self.env_step * self.tc.n_envs,
                               "updates": self.agent.updates, "time_s": round(self.elapsed + self._session_time(), 2),
                               "fps": round(fps, 1), "updates_per_s": round(ups, 2),
                               "noise_std": round(self.noise_std(), 4)}
        for r in ROLES:
            row[f"reward_{r}"] = win.reward[r] / n if r in self.role_idx else ""
            row[f"return_{r}"] = float(np.mean(win.returns[r])) if win.returns[r] else ""
        row["min_dist"], row["avg_dist"], row["max_dist"] = (win.dist / n).tolist()
        row["captures_per_step"] = win.captures / n
        row["episodes"] = len(win.returns[next(iter(self.role_idx))])
        row["teacher_share"] = round(self.teacher_share(), 4) if self.teacher is not None else ""
        for k in ("critic_loss", "actor_loss", "q_mean", "int8_sensitivity", "imitation_mse"):
            row[k] = win.losses[k] / win.n_updates if win.n_updates and k in win.losses else ""
        if win.n_clone:  # the extra cloning steps' figure: the same quantity, on more samples
            row["imitation_mse"] = win.clone_mse / win.n_clone
        with (self.out / "metrics.csv").open("a", newline="") as fh:
            csv.writer(fh).writerow([_fmt(row[c]) for c in CSV_COLUMNS])
        for k, v in row.items():
            if k != "step" and v != "":
                writer.add_scalar(k, float(v), self.env_step)
        return row


def _set_numba_threads(n: int) -> None:
    """Numba's parallel kernels (the Voronoi areas) use ``train.threads`` threads too: on a shared machine a
    second, spinning worker per run costs as much CPU as the run itself and buys nothing."""
    import numba
    numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def _postfix(row: dict[str, Any]) -> str:
    parts = [f"{r[0]}R={row[f'reward_{r}']:.2f}" for r in ROLES if row[f"reward_{r}"] != ""]
    parts.append(f"dmin={row['min_dist']:.2f} davg={row['avg_dist']:.2f}")
    parts.append(f"{row['fps']:.0f}fps {row['updates_per_s']:.1f}up/s")
    return " ".join(parts)


def install_stop_handlers() -> Any:
    """Make SIGINT (Ctrl-C) and SIGTERM (``kill PID``) stop training with a checkpoint, also for a run started
    in the background (where the shell sets SIGINT to be ignored); returns a function restoring the old
    handlers. Only possible in the main thread; elsewhere a no-op."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def stop(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}

    def restore() -> None:
        for sig, h in old.items():
            signal.signal(sig, h)
    return restore


def _utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def resolve_config(config: str | Path | None, out: str | Path, resume: bool, **overrides: Any) -> ExperimentConfig:
    """The experiment config of a run: the TOML given (or, with ``resume``, the run's own ``config.toml``),
    with non-None ``overrides`` of ``TrainConfig`` fields applied (validated)."""
    if resume:
        path = Path(out) / "config.toml"
        if not path.is_file():
            raise RunError(f"nothing to resume in {out}: {path} does not exist")
        if config is not None:
            log.info("--resume: using %s, not %s", path, config)
        cfg = ExperimentConfig.from_toml(path)
    else:
        if config is None:
            raise RunError("give --config CONFIG.toml (or --resume an existing run)")
        cfg = ExperimentConfig.from_toml(config)
    changes = {k: v for k, v in overrides.items() if v is not None}
    if changes:
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **changes))
    return cfg


def train(cfg: ExperimentConfig, out: str | Path, resume: bool = False, progress: bool = True,
          init_from: str | Path | None = None) -> TrainResult:
    """Train (or continue) the run in ``out``; Ctrl-C saves a checkpoint and returns with ``interrupted``.
    ``init_from``: a run folder whose last checkpoint this new run starts from (a fine-tune)."""
    trainer = Trainer(cfg, out, resume=resume, init_from=init_from)
    if resume:  # a resumed run records the (possibly extended) config it continues with
        write_text_atomic(trainer.out / "config.toml", dump_toml(cfg.to_dict()))
    return trainer.run(progress=progress)


# ------------------------------------------------------------------------------------------------ CLI
# registered by training.cli as `swarm-train train`


def add_train_parser(sub: Any) -> None:
    from runtime.cliutil import out_dir, positive_int
    p = sub.add_parser(
        "train", help="train Role-based MADDPG (all roles at once, evaders included)",
        description="Trains every agent of a config with Role-based MADDPG and writes a run folder: config.toml, "
                    "run.json (git revision), metrics.csv, tb/ (TensorBoard), checkpoints/ and actors.pt. "
                    "Ctrl-C saves a checkpoint; --resume continues it.")
    p.add_argument("--config", metavar="PATH", help="experiment TOML (not needed with --resume)")
    p.add_argument("--out", required=True, type=out_dir, metavar="RUN", help="run folder, e.g. runs/role_based")
    p.add_argument("--steps", type=positive_int, metavar="N", help="env steps per env to reach (overrides train.steps)")
    p.add_argument("--seed", type=int, metavar="S", help="training seed (overrides train.seed)")
    p.add_argument("--device", metavar="D", help="torch device: cpu, cuda or cuda:K (overrides train.device)")
    p.add_argument("--n-envs", type=positive_int, metavar="K", help="envs stepped together (overrides train.n_envs)")
    p.add_argument("--threads", type=positive_int, metavar="T", help="torch CPU threads (overrides train.threads)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--init-from", metavar="RUN",
                   help="start this new run from RUN's last checkpoint (networks, optimizers, replay buffer, env "
                        "step) and go on under --config up to its train.steps: a fine-tune, e.g. "
                        "configs/role_based_int8.toml from runs/role_based")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)


def cmd_train(args: Any) -> int:
    from training.cli import UsageError
    try:
        cfg = resolve_config(args.config, args.out, args.resume, steps=args.steps, seed=args.seed,
                             device=args.device, n_envs=args.n_envs, threads=args.threads)
        if args.resume and args.seed is not None:
            raise RunError("--seed cannot change on --resume: the run keeps its own seed")
        out = Path(args.out)
        if args.init_from is not None and not (Path(args.init_from) / "checkpoints" / "state.pt").is_file():
            raise RunError(f"--init-from {args.init_from}: nothing to start from, "
                           f"{Path(args.init_from) / 'checkpoints' / 'state.pt'} does not exist; give a run "
                           f"folder that `swarm-train train` wrote")
        created = not out.exists()  # removed again when the run fails to start: no half-made run folder
        handler = logging.FileHandler(out / "train.log") if out.is_dir() else None
        if handler is None:
            out.mkdir(parents=True, exist_ok=True)
            handler = logging.FileHandler(out / "train.log")
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        logging.getLogger().addHandler(handler)
        logging.getLogger().setLevel(min(logging.getLogger().level or logging.INFO, logging.INFO))
        try:
            result = train(cfg, out, resume=args.resume, progress=not args.no_progress, init_from=args.init_from)
        except BaseException:
            # a run that never reached its first checkpoint leaves no half-made folder behind (whatever failed:
            # a bad setting, no CUDA, Ctrl-C during start-up); one with a checkpoint is kept for --resume
            logging.getLogger().removeHandler(handler)
            handler.close()
            if created and not (out / "checkpoints" / "state.pt").is_file():
                import shutil
                shutil.rmtree(out, ignore_errors=True)
            raise
    except RunError as exc:
        raise UsageError(str(exc)) from None
    d = result.to_dict()
    state = "interrupted" if result.interrupted else "finished"
    print(f"{cfg.name}: {state} at env step {result.env_steps}: {d['frames']} frames and {d['updates']} updates "
          f"in {d['train_time_s']:.1f} s ({d['fps']:.0f} frames/s, {d['updates_per_s']:.1f} updates/s)")
    print(f"wrote {out / 'actors.pt'}" + (f"; continue with: swarm-train train --out {out} --resume"
                                          if result.interrupted else ""))
    return 130 if result.interrupted else 0
