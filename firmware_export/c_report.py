"""Evidence for a C export: parity of the host-compiled C against onnxruntime on random and simulator-recorded
observations, and the Cortex-M4 cost (flash, RAM, executed instructions, estimated cycles)."""
from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_export import m4_emu
from firmware_export.c_export import CExport
from firmware_export.toolchain import HostPolicy, build_host_library
from runtime.observation import encode_observations, new_knowledge, update_knowledge
from runtime.spec import Role, SwarmSpec
from runtime.world import World

HOST_FLAGS = ("-O2", "-ffast-math")


def random_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0) -> np.ndarray:
    """``n`` observations uniform within the layout's per-index ranges, float32 ``[n, obs_dim]``."""
    lo, hi = spec.layout(role).bounds()
    return np.random.default_rng(seed).uniform(lo, hi, (n, len(lo))).astype(np.float32)


def recorded_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0, n_envs: int = 16) -> np.ndarray:
    """``n`` observations of agents of ``role`` recorded from the world under random actions (the encoder
    training and flight use), float32 ``[n, obs_dim]``."""
    world = World(spec, n_envs=n_envs, seed=seed)
    rng = np.random.default_rng(seed + 1)
    st = world.reset()
    knowledge = new_knowledge(spec, n_envs)
    who = np.array(spec.team.indices(role))
    dim = spec.obs_dim(role)
    rows: list[np.ndarray] = []
    got = 0
    while got < n:
        t = st.step * spec.timing.control_period
        update_knowledge(spec, knowledge, st.pos, st.vel, t)
        obs = encode_observations(spec, st.pos, st.vel, st.obstacle_pos, st.obstacle_radius, knowledge, t,
                                  observers=who)
        block = obs[..., :dim].reshape(-1, dim)
        rows.append(block)
        got += block.shape[0]
        world.step(rng.uniform(-1.0, 1.0, (n_envs, spec.n_agents, 2)))
        done = st.step >= spec.timing.episode_steps
        if done.any():
            world.reset(np.nonzero(done)[0])
            knowledge[done] = new_knowledge(spec, int(done.sum()))
    return np.concatenate(rows)[:n].astype(np.float32)


def parity_observations(spec: SwarmSpec, role: Role, n: int, seed: int = 0) -> np.ndarray:
    """Half random within the spec's ranges, half recorded from the simulator."""
    return np.concatenate([random_observations(spec, role, n - n // 2, seed),
                           recorded_observations(spec, role, n // 2, seed)])


def onnx_actions(model_path: str | Path, obs: np.ndarray) -> np.ndarray:
    import onnxruntime as ort

    sess = ort.InferenceSession(str(model_path), providers=["CPUExecutionProvider"])
    name = sess.get_inputs()[0].name
    return sess.run(None, {name: np.ascontiguousarray(obs, dtype=np.float32)})[0]


def host_policy(export: CExport, work: Path) -> HostPolicy:
    lib = build_host_library([export.source], work / f"libswarm_policy_{export.quant}.so", HOST_FLAGS)
    return HostPolicy(lib, export.model.obs_dim, export.model.act_dim)


@dataclass(frozen=True)
class CostReport:
    n_obs: int
    host_max_abs_diff: float
    m4_sizes: m4_emu.SectionSizes
    m4_max_abs_diff: float
    m4_run: m4_emu.M4Run
    table_bytes: int

    @property
    def us(self) -> float:
        return m4_emu.micros(self.m4_run.cycles)

    @property
    def us_flash_bound(self) -> float:
        return m4_emu.micros(self.m4_run.cycles + m4_emu.flash_penalty_cycles(self.table_bytes))


def cost_report(export: CExport, model_path: str | Path, n_obs: int = 10_000, n_m4: int = 20,
                seed: int = 0) -> CostReport:
    spec, role = export.model.spec, export.model.role
    obs = parity_observations(spec, role, n_obs, seed)
    ref = onnx_actions(model_path, obs)
    with tempfile.TemporaryDirectory(prefix="swarm_c_") as tmp:
        work = Path(tmp)
        host = host_policy(export, work).act_batch(obs)
        build = m4_emu.build(export.source, work / "m4")
        pick = np.linspace(0, n_obs - 1, n_m4).astype(int)
        m4_acts = np.array([m4_emu.run(build, obs[i], count=False).act for i in pick])
        counted = m4_emu.run(build, obs[pick[-1]])  # a recorded observation
    return CostReport(n_obs, float(np.abs(host - ref).max()), build.sizes, float(np.abs(m4_acts - ref[pick]).max()),
                      counted, export.sources.weight_bytes)


def format_report(export: CExport, r: CostReport) -> str:
    m, s, run = export.model, r.m4_sizes, r.m4_run
    lines = [
        f"model {m.source}: agent {m.agent_id}, role {m.role.label}, spec {m.spec.hash}, "
        f"{' -> '.join([str(m.obs_dim)] + [str(d.n_out) for d in m.layers])}, weights {export.quant}, tanh {export.tanh}",
        f"parity vs onnxruntime, {r.n_obs} observations (half random in the spec's ranges, half recorded from the "
        f"simulator): host C max |diff| {r.host_max_abs_diff:.3g}; emulated Cortex-M4 build max |diff| "
        f"{r.m4_max_abs_diff:.3g} (on {20} of them)",
        "Cortex-M4 build (arm-none-eabi-gcc -O2 -ffast-math -mcpu=cortex-m4 -mfpu=fpv4-sp-d16 -mfloat-abi=hard):",
        f"  flash: code {s.text} B + tables {s.rodata} B = {s.text + s.rodata} B; "
        f"RAM: static {s.data + s.bss} B, stack {s.stack} B",
        f"  executed instructions per inference: {run.instructions}",
        f"  estimated cycles (TRM timing model, zero-wait memory): {run.cycles} = {r.us:.1f} us at 168 MHz",
        f"  bound with every table line read from flash at 5 wait states: {r.us_flash_bound:.1f} us",
        "  by class (instructions, cycles): " + "; ".join(f"{k} {n}/{c}" for k, (n, c) in run.by_class.items()),
    ]
    return "\n".join(lines)
