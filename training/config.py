"""Experiment configuration: one TOML file maps onto ``ExperimentConfig`` (unknown keys are errors).

```toml
name = "role_based"
[spec.team]        # runtime.spec.SwarmSpec tables: arena, pursuer, scout, evader, team, sensing, timing
n_pursuers = 5
[rewards]          # RewardConfig
collision_penalty = 10.0
[train]            # TrainConfig
steps = 200000
```
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from runtime.spec import SpecError, SwarmSpec, from_mapping, load_toml
from runtime.tomlmap import SECTION_NAMES

MAX_BUFFER = 5_000_000
"""The bound of train.buffer_size: a role_based transition (12 agents' observations, next observations, actions,
rewards, teacher actions) is about 5 KB, so 5 million are about 25 GB."""


@dataclass(frozen=True)
class RewardConfig:
    """Constants of the paper's equations (1)-(5) and Algorithm 1."""

    boundary_c1: float = 10.0
    """Cap c1 of the x boundary term -min(exp(3|x| - 9), c1) (eq. 1)."""
    boundary_c2: float = 10.0
    """Cap c2 of the y boundary term (eq. 1)."""
    boundary_gain: float = 3.0
    """The 3 in exp(3|x| - 9); the 9 is boundary_gain x arena half width (3 m), as in the paper."""
    collision_penalty: float = 10.0
    """c3 (eq. 2): subtracted for every other agent in contact (distance <= R_i + R_j), teammates and
    evader-evader pairs; pursuer-team/evader contacts are captures, rewarded below instead."""
    obstacle_penalty: float = 0.0
    """Subtracted while touching an obstacle (0 in the paper: obstacles are solid in the world)."""
    capture_reward: float = 20.0
    """CR_p (eq. 3): added to a pursuer for every evader it touches."""
    distance_weight: float = 1.0
    """DR_p (eq. 3) = -distance_weight x mean distance from the pursuer to the evaders [1/m]."""
    captured_penalty: float = 10.0
    """CR_e (eq. 4): subtracted from an evader for every pursuer or scout touching it."""
    exploration_weight: float = 1.0
    """E_i (eq. 5, Algorithm 1) = -exploration_weight x the largest bounded Voronoi cell area [1/m^2], every
    agent a seed."""
    # ---- options beyond the paper (each off in the paper configs) ----
    distance_mode: str = "mean"
    """DR_p: "mean" (eq. 3: the pursuer's own mean distance to the evaders, flat on the segment between two
    evaders, so it never asks a pursuer to commit to one) or "team" (team-aligned: every pursuer gets
    -distance_weight x the mean over evaders of the NEAREST pursuer's distance, the quantity that the
    tracking and minimum-distance metrics score, plus ``own_distance_weight`` x its own nearest-evader term)."""
    own_distance_weight: float = 0.0
    """With distance_mode = "team": adds -own_distance_weight x the pursuer's own distance to its nearest
    evader, the individual credit that keeps every pursuer busy [1/m]."""
    shared_capture: bool = False
    """CR_p shared (MPE's convention): every pursuer gets capture_reward for each evader touched by ANY pursuer,
    instead of only the pursuer that touched it."""
    pursuer_boundary: bool = True
    """Apply the boundary term (eq. 1) to pursuers (the paper does; evaders run for the walls, so a penalised
    pursuer hangs back where the targets are)."""
    proximity_penalty: float = 0.0
    """Soft teammate-proximity penalty [1/step]: each pursuer-team agent loses proximity_penalty x
    ramp(distance) per teammate closer than ``proximity_distance``, the ramp rising linearly from 0 there to
    1 at contact (R_i + R_j); 0 disables. Flight keeps drones ``separation.min_distance`` apart anyway: this
    teaches policies not to ask for it."""
    proximity_distance: float = 0.35
    """Centre distance [m] under which the proximity penalty starts (the flight's separation distance)."""

    def __post_init__(self) -> None:
        for name in ("boundary_c1", "boundary_c2", "boundary_gain", "collision_penalty", "obstacle_penalty",
                     "capture_reward", "distance_weight", "captured_penalty", "exploration_weight",
                     "own_distance_weight", "proximity_penalty", "proximity_distance"):
            if not getattr(self, name) >= 0:
                raise SpecError(f"rewards.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.distance_mode not in ("mean", "team"):
            raise SpecError(f"rewards.distance_mode: {self.distance_mode!r} is not one of 'mean', 'team'")
        if self.own_distance_weight and self.distance_mode != "team":
            raise SpecError("rewards.own_distance_weight: only used with distance_mode = 'team'; set it to 0 "
                            "or set distance_mode = 'team'")


@dataclass(frozen=True)
class TrainConfig:
    """Role-based MADDPG hyper-parameters (see ``training.maddpg`` and ``training.train``).

    Time is counted in env steps: one env step advances all ``n_envs`` environments by one control period
    and yields ``n_envs`` joint transitions (frames).
    """

    steps: int = 200_000
    """Environment steps per env to train for (total frames = steps x n_envs)."""
    n_envs: int = 64
    """Environments stepped in parallel."""
    seed: int = 0
    """Seed of the world, the networks and the replay sampling."""
    gamma: float = 0.95
    """Discount factor per control period [1] (the original MADDPG's 0.95)."""
    tau: float = 0.01
    """Soft target update rate per gradient update: target <- tau x online + (1 - tau) x target [1]."""
    actor_lr: float = 1e-3
    """Adam learning rate of the actors [1]."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critics [1]."""
    actor_hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of every actor (the export contract expects two layers)."""
    critic_hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of every centralized critic."""
    batch_size: int = 1024
    """Joint transitions per gradient update."""
    buffer_size: int = 200_000
    """Replay capacity in joint transitions (preallocated; oldest overwritten first)."""
    warmup_steps: int = 50
    """Env steps with uniformly random actions before learning starts."""
    update_every: int = 1
    """Env steps between two rounds of gradient updates."""
    updates_per_round: int = 1
    """Gradient updates (critics, then actors, then targets) per round."""
    noise_std: float = 0.3
    """Initial std of the Gaussian exploration noise added to the normalised actions [1]."""
    noise_std_final: float = 0.05
    """Exploration noise std reached after ``noise_decay_steps`` (linear decay) [1]."""
    noise_decay_steps: int = 10_000
    """Env steps over which the exploration noise decays to ``noise_std_final``."""
    grad_clip: float = 0.5
    """Max global gradient norm, per agent, of every actor and critic update (0 disables)."""
    action_reg: float = 1e-3
    """Weight of the penalty on squared pre-tanh actor outputs (keeps tanh out of saturation) [1]."""
    int8_robustness: float = 0.0
    """Weight of the int8-robustness penalty on every actor (0 disables) [1]: the mean squared change of the
    actions when each hidden layer's weights get uniform noise of one int8 step (``max|w| / 127`` per output
    neuron, the C export's ``--quant int8w`` scale), plus the mean of the worst 5 % of those changes, on the
    batch's observations and as many drawn uniformly within the spec's per-field ranges (the observations
    the C export is checked on). It trains actors whose int8 export stays close to the float one; see
    results/c_export_report.md."""
    reward_scale: float = 0.1
    """Multiplies every reward in the learner only (the env's rewards stay the paper's) [1]."""
    evaders: str = "learned"
    """"learned": evaders train at the same time (competitive co-training); "static": evaders hold still
    (their actors are not trained; used for the small learning check); "scripted": evaders flee as
    ``training.baselines.FleeingEvaders`` (their actors are not trained)."""
    opponent_mix: float = 0.0
    """Opponent mixing (fictitious self-play, ``training.opponents``): the share of episodes whose evaders are
    not the learners but a scripted evader of ``training.evader_suite.TrainingPool`` or a frozen snapshot of
    earlier learned evaders; 0 disables (the paper's co-training) [1]."""
    opponent_scripted: float = 0.5
    """Of the mixed episodes, the share with scripted evaders (the rest meet snapshots) [1]."""
    opponent_snapshot_every: int = 1_000
    """Env steps between two snapshots of the learned evaders."""
    opponent_snapshots: int = 5
    """Newest snapshots kept (older ones are dropped)."""
    log_every: int = 100
    """Env steps between two rows of metrics.csv and TensorBoard scalars."""
    checkpoint_every: int = 2_000
    """Env steps between two full training-state checkpoints (also written on Ctrl-C and at the end)."""
    snapshot_actors: bool = False
    """Also keep the actors of every checkpoint as ``snapshots/actors_<env step>.pt`` (``actors.pt`` holds only the
    newest), so that a run's course can be evaluated afterwards (``swarm-train evaluate --run RUN --actors
    snapshots/actors_006000.pt``)."""
    checkpoint_buffer: bool = True
    """Also save the replay buffer with each checkpoint, so that --resume continues exactly (and --init-from and
    the int8 clone start from it). It is the big file of a run folder: ``checkpoints/buffer.pt`` is 776 MB for
    configs/role_based.toml's 200,000 transitions; delete it from a finished run you will not resume or fine-tune."""
    threads: int = 2
    """torch CPU threads."""
    device: str = "cpu"
    """torch device of the networks and the replay buffer: "cpu", "cuda" or "cuda:K"."""
    algorithm: str = "maddpg"
    """"maddpg": one critic per agent (the paper's); "matd3": twin critics with the smaller target, target
    policy smoothing and delayed actor and target updates (Ackermann et al. 2019, TD3 for many agents)."""
    policy_delay: int = 2
    """"matd3" only: critic updates per actor update (and per soft target update)."""
    target_noise: float = 0.2
    """"matd3" only: std of the Gaussian noise on the target actors' next actions (target policy smoothing)
    [1, normalised action]."""
    target_noise_clip: float = 0.5
    """"matd3" only: the target smoothing noise is clipped to +-this [1, normalised action]."""
    critic: str = "local"
    """Centralized critics: "local": one per agent on every agent's observation concatenated (N x max_obs_dim;
    the paper's); "global": one per agent on the compact global state (every agent's position and velocity,
    every obstacle's centre and radius: 4N + 3K floats, ``training.maddpg.global_state``); "role": one per role
    on the global state with a head per agent of the role, and a role-level centralized policy gradient
    (``training.rolecritic``; 3 critics instead of 12 for role_based). All also take every action."""
    share_params: bool = False
    """Parameter sharing within a role: one actor and one critic per role, trained on all of that role's
    agents' transitions (the critic gets a one-hot of which agent of the role it evaluates); still exported
    as one actor per agent."""
    obs_scaling: bool = False
    """Actors see observations mapped from the spec's per-field ranges (``spec.layout(role).bounds()``) to
    [-1, 1]; the map is folded into the first layer on export, so exported actors take raw observations."""
    obs_offset_gain: float = 1.0
    """With ``obs_scaling``: the relative offsets (every field's ``dx``, ``dy`` columns: targets, teammates,
    obstacles) are scaled this many times more than their range asks ([-6, 6] m -> [-gain, gain]), so that the
    first layer resolves centimetres near a target without weights that Adam's small steps take tens of
    thousands of updates to grow. Folded into the first layer on export like the rest of the scaling."""
    teacher: str = "none"
    """A teacher for the actors: "none" (the paper's), or "classical": ``training.baselines.ClassicalPursuers``
    for the pursuer team's rows and ``FleeingEvaders`` for the evaders' (the classical team, which reads the
    true state). Its actions are recorded with every transition; ``imitation_steps`` and
    ``imitation_weight`` say how the actors learn from them."""
    teacher_separation_gain: float = 3.0
    """The classical teacher's teammate push at zero distance (``ClassicalPursuers.separation_gain``; 3 is the
    classical team's, the bar every evaluation compares with). Students fly through ``[spec.avoidance]``, which
    keeps teammates apart by itself; a gentler push leaves their labels near a crowded target closer to pursuit
    (``results/issue13/label_source.py``)."""
    teacher_obstacle_softness: float = 0.0
    """The classical teacher's ``ClassicalPursuers.obstacle_side_softness``: 0 (the classical team's): next to an
    obstacle it slides to the side its wish leans to, a label that flips side when the target is straight behind
    the obstacle, where a clone that averages the two sides stalls; > 0 (e.g. 0.3): the slide fades out there
    instead, a continuous label (the teacher as strong: ``results/issue13/teacher_obstacle.py``)."""
    teacher_assignment: str = "central"
    """How the classical teacher splits its pursuers between the evaders (``ClassicalPursuers.assignment``):
    "central" (the classical team's: one Hungarian assignment over every pursuer, which reads the whole state), or
    "local": each pursuer's own over itself and the teammates its observation lists, a label that is a function of
    what the student sees (``results/issue13/assignment_info.py``)."""
    teacher_lead_time: float = 0.6
    """The classical teacher's longest look-ahead [s] on its target (``ClassicalPursuers.lead_time_max``; 0.6 is the
    classical team's)."""
    teacher_lead_others: float = 0.6
    """The classical teacher's look-ahead [s] for a pursuer that is not the nearest to its target among those
    assigned to it (``ClassicalPursuers.lead_time_others``): the nearest leads by ``teacher_lead_time`` and closes
    in, the others head further ahead. Equal to ``teacher_lead_time`` (the default): one lead for all, the classical
    team's (``results/issue13/teacher_variants.py``, ``duo``)."""
    teacher_side_lead: float | None = None
    """None (the default, the classical team's): one look-ahead wherever the target flies. A number [s]: the teacher's
    look-ahead on a target flying ``teacher_side_angle`` or more off the bearing from the pursuer
    (``ClassicalPursuers.lead_side_time``), from ``teacher_lead_time`` along the bearing, linear in the angle's cosine,
    so that a target running sideways, which may turn back, is led less (results/issue13/teacher_side_lead.py). Left
    out of a run's config.toml while None (TOML has no null)."""
    teacher_side_angle: float = 60.0
    """The angle [deg] off the bearing at which the teacher's look-ahead reaches ``teacher_side_lead``."""
    teacher_side_wall: float | None = None
    """None (the default): ``teacher_side_lead`` applies wherever the target is. A number [m]: only to a target at least
    this far plus ``ClassicalPursuers.lead_side_fade`` from every wall, fading to none at this distance
    (``ClassicalPursuers.lead_side_wall``), so that a target running along a wall is led by ``teacher_lead_time``
    (results/issue13/teacher_side_wall.py). Needs ``teacher_side_lead``."""
    teacher_scout_sweep: float | None = None
    """None (the default, the classical team's): the teacher's scouts take Lloyd's step alone and settle at their
    cells' centroids. A number [normalized action]: added to their Lloyd's step, a wish of this size that keeps them
    moving (``ClassicalPursuers.scout_sweep``), so that the team sees more of the arena over an episode
    (results/issue13/teacher_scout_sweep.py). Left out of a run's config.toml while None."""
    teacher_scout_sweep_clear: float | None = None
    """None (the default): ``teacher_scout_sweep`` applies however near the evaders a scout is. A number [m]: only to
    a scout at least this far plus ``ClassicalPursuers.scout_sweep_fade`` from every evader, fading to none at this
    distance (``ClassicalPursuers.scout_sweep_clear``): near a chase the scouts hold Lloyd's spread. Needs
    ``teacher_scout_sweep``."""
    teacher_scout_sweep_mode: str = "heading"
    """What ``teacher_scout_sweep`` adds (``ClassicalPursuers.scout_sweep_mode``): "heading": along the scout's own
    velocity; "orbit": counter-clockwise about the arena's centre."""
    imitation_steps: int = 0
    """The first env steps learn by DAgger (Ross et al. 2011): each env acts with the teacher with probability
    beta (1 at the start, 0 at the end, linear) and with the learners' noisy actions otherwise, and the actor
    steps regress every actor onto the teacher's actions (the critics learn from these transitions as
    always, so they are warm when reinforcement learning takes over). 0: none."""
    imitation_weight: float = 0.0
    """After ``imitation_steps``: the actor loss is TD3+BC's ``-Q / mean|Q| + w x |mu - teacher|^2``
    (Fujimoto and Gu 2021), which keeps the actors near the teacher while the critics improve on it. 0: the
    paper's actor loss."""
    imitation_decay_steps: int = 0
    """Env steps after ``imitation_steps`` over which ``imitation_weight`` falls linearly to 0, so that the actors
    can leave the teacher where the critics know better; 0: it stays constant."""
    imitation_updates: int = 0
    """Extra behaviour-cloning steps of the actors per env step during the imitation phase, each on its own
    replay sample of ``imitation_batch`` transitions (the DAgger data: every stored transition carries the
    teacher's action), besides the regular updates; 0: none. Cloning a teacher well takes far more actor steps
    than the critics need."""
    imitation_batch: int = 1024
    """Transitions per extra behaviour-cloning step (``imitation_updates``)."""
    imitation_near_weight: float = 1.0
    """Weight of a behaviour-cloning row whose agent sees a known target within ``imitation_near_radius``,
    relative to 1 for every other row (a weighted mean over each agent's rows): the clone's error is largest
    next to a target (``results/issue13/clone_error.py``), where few of the DAgger rows are. 1: unweighted."""
    imitation_near_radius: float = 0.5
    """[m] How near a known target makes a row "near" for ``imitation_near_weight``."""
    imitation_obstacle_weight: float = 1.0
    """Weight of a behaviour-cloning row whose agent is within ``imitation_obstacle_radius`` of an obstacle's
    surface (times ``imitation_near_weight`` where both hold): there the teacher slides along the surface to the
    side its wish leans to, a label that flips side when the target is straight behind the obstacle, and a clone
    that averages the two sides stalls (``results/issue13/tracking_split.py``). 1: unweighted."""
    imitation_obstacle_radius: float = 0.3
    """[m] How near an obstacle's surface makes a row "near" for ``imitation_obstacle_weight`` (0.3: where the
    classical teacher's obstacle avoidance starts)."""
    imitation_obstacle_walls: bool = False
    """Count the arena's walls with the obstacles for ``imitation_obstacle_weight``: a row whose agent's body is
    within ``imitation_obstacle_radius`` of a wall weighs it too (the perimeter runner keeps its pursuers there,
    where the teacher's wall damping and the avoidance layer's wall barrier meet)."""
    imitation_augment: float = 0.0
    """Share of every behaviour-cloning batch (DAgger's and the polish's) drawn from augmented rows instead of the
    replay buffer: at every DAgger step, that step's states with every evader's velocity redrawn (a uniform heading,
    a speed uniform up to the evader's top speed), observed and labelled by the teacher anew (``CloneBuffer``). The
    DAgger rows hold the velocities the training evaders fly next to the team, mostly straight away from it, while
    the teacher's lead follows a target's velocity wherever it points. Measured, it did not bring the clone closer
    to the held-out juker (results/README.md, twenty-third attempt); off in every shipped config. 0: none."""
    imitation_polish_steps: int = 0
    """When the imitation (DAgger) phase ends: this many more behaviour-cloning steps of the team's actors
    (pursuers and scouts), each on its own replay sample of ``imitation_batch`` transitions, with no env steps,
    before reinforcement learning or ES go on. The clone is still learning the aggregated DAgger data when the
    phase ends (on the last 16,384 stored transitions, held out, 12,000 more steps cut the pursuers' error by a
    quarter: results/README.md, fifteenth attempt; yet ES from the closer clone did worse on the held-out evaders, so
    the shipped configs leave it off). The evaders' actors stay as the DAgger phase left them. 0: none."""
    es_iterations: int = 0
    """After the MADDPG steps: iterations of evolution strategies on the pursuer team's actors, scored on the
    evaluation's metrics against the training pool and the frozen co-trained evaders (``training.es``); 0: none.
    Needs ``share_params`` (one actor per role)."""
    es_population: int = 16
    """ES directions per iteration; each is flown as ``+sigma`` and ``-sigma`` (antithetic pairs)."""
    es_episodes: int = 16
    """Episodes every member of an ES population flies (the same ones for all: common random numbers)."""
    es_sigma: float = 0.003
    """Std of the ES perturbations of every actor weight [1]."""
    es_lr: float = 0.001
    """Adam step size of the ES ascent [1, per weight]."""
    es_tracking_weight: float = 1.0
    """ES fitness: + weight x tracking rate [1]."""
    es_distance_weight: float = 1.0
    """ES fitness: - weight x mean minimum pursuer-evader distance [1/m]."""
    es_coverage_weight: float = 0.1
    """ES fitness: + weight x episode coverage [1]."""
    es_contact_weight: float = 0.1
    """ES fitness: - weight x the team's own contacts per episode (teammates and obstacles) [1]."""
    es_capture_weight: float = 0.0
    """ES fitness: + weight x captures per episode (onsets of a pursuer-team agent touching an evader) [1]. The
    paper's pursuers are paid on contact; a clone of the classical team shadows its target a few centimetres off
    instead of touching it."""
    es_learned_share: float = 0.3
    """Share of ES episodes whose evaders are the run's co-trained actors (frozen); the rest meet the training
    pool (``training.evader_suite.TrainingPool``). The held-out suite and the scripted evaders are never met."""
    es_rank: str = "total"
    """How ES ranks its members: "total" (by mean fitness over the episodes) or "episode" (by mean rank within
    each episode, so that episodes against opponents with larger spreads of fitness do not outvote the rest)."""
    es_role_fitness: str = "team"
    """Which fitness each role's weights ascend (all from the same rollouts): "team": both the team's one fitness,
    so that a coverage weight large enough to move the scouts moves the pursuers off pursuit too; "split": the
    pursuers' the pursuit terms (tracking, distance, contacts, captures), the scouts' coverage and contacts;
    "pursuers": the pursuers' the pursuit terms, the scouts' the team's (they also help the pursuit)."""
    es_pool: tuple[str, ...] = ()
    """The training-pool behaviours ES's scripted episodes draw from (``training.evader_suite.POOL`` kinds);
    empty: all of them."""
    es_checkpoint_every: int = 5
    """ES iterations between two saves of the ES state and the actors."""
    es_pursuer_iterations: int | None = None
    """None (the default): every role's weights ascend in every ES iteration. A number k: the pursuers' only in the
    first k; after them the pursuers' actor is frozen (neither perturbed nor stepped) and only the other roles'
    weights go on for the rest of ``es_iterations`` (role_based: the pursuit that ES's first iterations reach, the
    scouts' coverage that the whole run reaches; results/README.md, twenty-ninth attempt). Left out of a run's
    config.toml while None."""

    def __post_init__(self) -> None:
        for name in ("steps", "n_envs", "batch_size", "buffer_size", "update_every", "log_every",
                     "checkpoint_every", "threads", "noise_decay_steps", "policy_delay"):
            if getattr(self, name) < 1:
                raise SpecError(f"train.{name}: must be >= 1, got {getattr(self, name)!r}")
        for name in ("seed", "warmup_steps", "updates_per_round"):  # numpy's generators take no negative seed
            if getattr(self, name) < 0:
                raise SpecError(f"train.{name}: must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 < self.gamma <= 1.0:
            raise SpecError(f"train.gamma: must be in (0, 1], got {self.gamma!r}")
        if not 0.0 < self.tau <= 1.0:
            raise SpecError(f"train.tau: must be in (0, 1], got {self.tau!r}")
        for name in ("actor_lr", "critic_lr", "reward_scale"):
            if not getattr(self, name) > 0:
                raise SpecError(f"train.{name}: must be > 0, got {getattr(self, name)!r}")
        for name in ("opponent_mix", "opponent_scripted"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise SpecError(f"train.{name}: must be in [0, 1], got {getattr(self, name)!r}")
        for name in ("opponent_snapshot_every", "opponent_snapshots"):
            if getattr(self, name) < 1:
                raise SpecError(f"train.{name}: must be >= 1, got {getattr(self, name)!r}")
        if self.opponent_mix > 0 and self.evaders != "learned":
            raise SpecError(f"train.opponent_mix: mixes opponents for learned evaders only (train.evaders = "
                            f"{self.evaders!r}): set it to 0 or train.evaders = 'learned'")
        for name in ("noise_std", "noise_std_final", "grad_clip", "action_reg", "int8_robustness", "target_noise",
                     "target_noise_clip"):
            if not getattr(self, name) >= 0:
                raise SpecError(f"train.{name}: must be >= 0, got {getattr(self, name)!r}")
        for name in ("actor_hidden", "critic_hidden"):
            widths = getattr(self, name)
            if not widths or any(w < 1 for w in widths):
                raise SpecError(f"train.{name}: must be a non-empty list of positive widths, got {list(widths)!r}")
        if self.buffer_size > MAX_BUFFER:
            raise SpecError(f"train.buffer_size: must be <= {MAX_BUFFER:,} transitions (the replay buffer is "
                            f"allocated when training starts), got {self.buffer_size!r}")
        if self.batch_size > self.buffer_size:
            raise SpecError(f"train.batch_size ({self.batch_size}) exceeds train.buffer_size ({self.buffer_size})")
        if self.evaders not in ("learned", "static", "scripted"):
            raise SpecError(f"train.evaders: {self.evaders!r} is not one of 'learned', 'static', 'scripted'")
        if not (self.device == "cpu" or self.device == "cuda" or self.device.startswith("cuda:")):
            raise SpecError(f"train.device: {self.device!r} is not 'cpu', 'cuda' or 'cuda:K'")
        if self.algorithm not in ("maddpg", "matd3"):
            raise SpecError(f"train.algorithm: {self.algorithm!r} is not one of 'maddpg', 'matd3'")
        if self.critic not in ("local", "global", "role"):
            raise SpecError(f"train.critic: {self.critic!r} is not one of 'local', 'global', 'role'")
        if self.teacher not in ("none", "classical"):
            raise SpecError(f"train.teacher: {self.teacher!r} is not one of 'none', 'classical'")
        if not (math.isfinite(self.teacher_separation_gain) and self.teacher_separation_gain >= 0):
            raise SpecError(f"train.teacher_separation_gain: must be a finite number >= 0, got "
                            f"{self.teacher_separation_gain!r}")
        for name in ("teacher_lead_time", "teacher_lead_others"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 <= v <= 5.0):  # the loader has checked it is a number
                raise SpecError(f"train.{name}: must be a look-ahead in [0, 5] s (0.6: the classical team's), got "
                                f"{v!r}")
        if self.teacher_side_lead is not None and not (math.isfinite(self.teacher_side_lead)
                                                       and 0.0 <= self.teacher_side_lead <= 5.0):
            raise SpecError(f"train.teacher_side_lead: must be a look-ahead in [0, 5] s, or left out for the classical "
                            f"team's one lead, got {self.teacher_side_lead!r}")
        self._check_fade("teacher_side_wall", "teacher_side_lead", "walls", "the side lead")
        if self.teacher_scout_sweep is not None and not (math.isfinite(self.teacher_scout_sweep)
                                                         and 0.0 <= self.teacher_scout_sweep <= 2.0):
            raise SpecError(f"train.teacher_scout_sweep: must be a wish in [0, 2] (normalized action), or left out for "
                            f"Lloyd's step alone, got {self.teacher_scout_sweep!r}")
        self._check_fade("teacher_scout_sweep_clear", "teacher_scout_sweep", "evaders", "the sweep")
        if self.teacher_scout_sweep_mode not in ("heading", "orbit"):
            raise SpecError(f"train.teacher_scout_sweep_mode: {self.teacher_scout_sweep_mode!r} is not one of "
                            f"'heading', 'orbit'")
        if not (math.isfinite(self.teacher_side_angle) and 0.0 < self.teacher_side_angle <= 180.0):
            raise SpecError(f"train.teacher_side_angle: must be an angle in (0, 180] degrees (60 by default), got "
                            f"{self.teacher_side_angle!r}")
        if not (math.isfinite(self.teacher_obstacle_softness) and self.teacher_obstacle_softness >= 0):
            raise SpecError(f"train.teacher_obstacle_softness: must be a finite number >= 0 (0: the classical "
                            f"team's), got {self.teacher_obstacle_softness!r}")
        if self.teacher_assignment not in ("central", "local"):
            raise SpecError(f"train.teacher_assignment: {self.teacher_assignment!r} is not one of 'central', 'local'")
        if self.imitation_steps < 0 or self.imitation_steps > self.steps:
            raise SpecError(f"train.imitation_steps: must be in [0, train.steps = {self.steps}], got "
                            f"{self.imitation_steps!r}")
        if not self.imitation_weight >= 0:
            raise SpecError(f"train.imitation_weight: must be >= 0, got {self.imitation_weight!r}")
        for name in ("imitation_decay_steps", "imitation_updates", "imitation_polish_steps"):
            if getattr(self, name) < 0:
                raise SpecError(f"train.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.es_iterations < 0:
            raise SpecError(f"train.es_iterations: must be >= 0, got {self.es_iterations!r}")
        if self.es_pursuer_iterations is not None and not 0 <= self.es_pursuer_iterations <= self.es_iterations:
            raise SpecError(f"train.es_pursuer_iterations: must be in [0, train.es_iterations = {self.es_iterations}] "
                            f"(the ES iterations in which the pursuers' weights move), or left out for all of them, "
                            f"got {self.es_pursuer_iterations!r}")
        for name in ("es_population", "es_episodes", "es_checkpoint_every"):
            if getattr(self, name) < 1:
                raise SpecError(f"train.{name}: must be >= 1, got {getattr(self, name)!r}")
        for name in ("es_sigma", "es_lr"):
            if not getattr(self, name) > 0:
                raise SpecError(f"train.{name}: must be > 0, got {getattr(self, name)!r}")
        for name in ("es_tracking_weight", "es_distance_weight", "es_coverage_weight", "es_contact_weight",
                     "es_capture_weight"):
            if not getattr(self, name) >= 0:
                raise SpecError(f"train.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.es_role_fitness not in ("team", "split", "pursuers"):
            raise SpecError(f"train.es_role_fitness: must be \"team\", \"split\" or \"pursuers\", got "
                            f"{self.es_role_fitness!r}")
        if self.es_role_fitness == "split" and not self.es_coverage_weight > 0:
            raise SpecError("train.es_role_fitness = \"split\": the scouts' fitness is coverage (and contacts): set "
                            "train.es_coverage_weight > 0")
        if self.es_rank not in ("total", "episode"):
            raise SpecError(f"train.es_rank: must be \"total\" or \"episode\", got {self.es_rank!r}")
        from training.evader_suite import POOL
        bad = [k for k in self.es_pool if k not in POOL]
        if bad or len(set(self.es_pool)) != len(self.es_pool):
            raise SpecError(f"train.es_pool: {bad or list(self.es_pool)!r}: give distinct kinds of the training pool "
                            f"{sorted(POOL)} (or [] for all)")
        if not 0.0 <= self.es_learned_share <= 1.0:
            raise SpecError(f"train.es_learned_share: must be in [0, 1], got {self.es_learned_share!r}")
        if self.es_iterations and not self.share_params:
            raise SpecError("train.es_iterations: evolution strategies fly one actor per role: set "
                            "train.share_params = true (or train.es_iterations = 0)")
        if not (math.isfinite(self.imitation_near_weight) and self.imitation_near_weight > 0):
            raise SpecError(f"train.imitation_near_weight: must be a finite number > 0 (1: unweighted), got "
                            f"{self.imitation_near_weight!r}")
        if not (math.isfinite(self.imitation_obstacle_weight) and self.imitation_obstacle_weight > 0):
            raise SpecError(f"train.imitation_obstacle_weight: must be a finite number > 0 (1: unweighted), got "
                            f"{self.imitation_obstacle_weight!r}")
        if self.imitation_obstacle_walls and self.imitation_obstacle_weight == 1.0:
            raise SpecError("train.imitation_obstacle_walls: weighs the rows next to a wall by "
                            "train.imitation_obstacle_weight, which is 1 (unweighted): set it, or the walls to false")
        if not (math.isfinite(self.imitation_obstacle_radius) and self.imitation_obstacle_radius > 0):
            raise SpecError(f"train.imitation_obstacle_radius: must be a finite distance > 0 [m], got "
                            f"{self.imitation_obstacle_radius!r}")
        if not (math.isfinite(self.imitation_near_radius) and self.imitation_near_radius > 0):
            raise SpecError(f"train.imitation_near_radius: must be a finite distance > 0 [m], got "
                            f"{self.imitation_near_radius!r}")
        if self.imitation_polish_steps and not (self.imitation_steps and self.teacher != "none"):
            raise SpecError("train.imitation_polish_steps: polishes the clone of a DAgger phase, and this config has "
                            "none: set train.teacher and train.imitation_steps, or imitation_polish_steps = 0")
        if not (math.isfinite(self.imitation_augment) and 0.0 <= self.imitation_augment < 1.0):
            raise SpecError(f"train.imitation_augment: must be a share in [0, 1) of each cloning batch (0: none), got "
                            f"{self.imitation_augment!r}")
        if self.imitation_augment and not (self.imitation_steps and self.teacher != "none"):
            raise SpecError("train.imitation_augment: augments the rows of a DAgger phase, and this config has none: "
                            "set train.teacher and train.imitation_steps, or imitation_augment = 0")
        if self.imitation_batch < 1:
            raise SpecError(f"train.imitation_batch: must be >= 1, got {self.imitation_batch!r}")
        if self.imitation_updates and self.imitation_batch > self.buffer_size:
            raise SpecError(f"train.imitation_batch ({self.imitation_batch}) exceeds train.buffer_size "
                            f"({self.buffer_size})")
        if (self.imitation_steps > 0 or self.imitation_weight > 0 or self.imitation_updates > 0) \
                and self.teacher == "none":
            raise SpecError("train.imitation_steps / train.imitation_weight learn from a teacher: set "
                            "train.teacher = 'classical' (or both to 0)")
        if self.teacher != "none" and self.evaders == "static":
            raise SpecError("train.teacher: the classical teacher's evaders flee; train.evaders = 'static' holds "
                            "them still: use train.evaders = 'learned' or 'scripted'")
        if not (math.isfinite(self.obs_offset_gain) and self.obs_offset_gain > 0):
            raise SpecError(f"train.obs_offset_gain: must be a finite number > 0, got {self.obs_offset_gain!r}")
        if self.obs_offset_gain != 1.0 and not self.obs_scaling:
            raise SpecError(f"train.obs_offset_gain = {self.obs_offset_gain!r} scales the scaled inputs: set "
                            f"train.obs_scaling = true, or leave obs_offset_gain at 1")
        for name in ("share_params", "obs_scaling", "imitation_obstacle_walls"):
            if not isinstance(getattr(self, name), bool):
                raise SpecError(f"train.{name}: must be true or false, got {getattr(self, name)!r}")

    def _check_fade(self, name: str, base: str, near: str, what: str) -> None:
        """``name``: a distance [m] from the ``near`` (walls, evaders) that fades option ``base`` out, or None."""
        v = getattr(self, name)
        if v is None:
            return
        if getattr(self, base) is None:
            raise SpecError(f"train.{name}: fades out train.{base} near the {near}; set {base} too, or leave {name} "
                            f"out")
        if not (math.isfinite(v) and 0.0 <= v <= 10.0):
            raise SpecError(f"train.{name}: must be a distance from the {near} in [0, 10] m, or left out for {what} "
                            f"everywhere, got {v!r}")


@dataclass(frozen=True)
class ExperimentConfig:
    name: str = "default"
    """Short name used for run folders and reports."""
    spec: SwarmSpec = field(default_factory=SwarmSpec)
    rewards: RewardConfig = field(default_factory=RewardConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    @classmethod
    def from_dict(cls, data: dict[str, Any], where: str = "config") -> "ExperimentConfig":
        return from_mapping(cls, data, where)

    @classmethod
    def from_toml(cls, path: str | Path) -> "ExperimentConfig":
        """The experiment in TOML file ``path``; a wrong key or value is a ``SpecError`` that starts with the
        file and names the key as its table spells it (``PATH: train.stepz: unknown key; valid keys are ...``)."""
        doc = load_toml(path)
        top = "<top>"  # from_mapping's prefix of top-level keys: dropped, the message starts with the path
        try:
            return from_mapping(cls, doc, top)
        except SpecError as exc:
            msg = str(exc)
            msg = msg[len(top) + 1:] if msg.startswith(top + ".") else msg.replace(top, "the file's top level")
            key, colon, rest = msg.partition(": ")  # a table's own checks name it again: train.train.seed
            msg = re.sub(r"(?<![\w\[])(\w+)\.\1(?![\w])", r"\1", key) + colon + rest
            raise SpecError(f"{path}: {msg}") from None

    def to_dict(self) -> dict[str, Any]:
        import dataclasses
        return {"name": self.name, "spec": self.spec.to_dict(), "rewards": dataclasses.asdict(self.rewards),
                "train": dataclasses.asdict(self.train)}


# a table's own checks say train.x / rewards.x: from_mapping puts the full path in front instead of repeating it
SECTION_NAMES.update({"TrainConfig": "train", "RewardConfig": "rewards"})
