"""The C twin of the avoidance layer (``swarm_avoid`` in the Crazyflie app's swarm_logic.c, its numbers generated
into policy.h by firmware_export/cgen_avoid.py) against the Python kernel ``runtime.avoidance.avoid_rows``, and
the app's action-to-velocity against the runtime's.

How C and Python are compared. Both enumerate the same candidates in the same order and keep the nearest
feasible one, the C in float32 from the same float32 observation and action, the kernel in float64. Each side's
constraints differ from the exact ones by rounding: the C's limits by at most ``LIMIT_ERR`` (a gap of numbers up
to the half width, 3-4 float32 roundings of 3 m, times the limit's steepest slope ``1/dt``: 9.5e-6 m/s at
dt = 0.1 s) and its normals by a few float32 epsilons; the C accepts a candidate up to ``SWARM_AVOID_FEASIBLE_TOL``
beyond a constraint (``cgen_avoid.c_feasible_tol``, argued there: 64 eps x the largest velocity, ~1e-5 m/s), and
its action is stored in float32. ``SAT_TOL``, their sum, bounds how far the C's velocity may be outside the exact
constraints (checked on every row: every half-plane, the speed disc, and the reachability disc whenever Python's
answer is reachable). Where the optimum has one active constraint, or two meeting at an angle whose sine is at
least 0.4, perturbing the constraints by ``SAT_TOL`` moves it by at most ``2 SAT_TOL / 0.4``: ``POINT_TOL`` =
5 SAT_TOL (~1e-4 m/s), the bound on |C - Python| in velocity. A row beyond it must be a near-tie (two
candidates, or a narrow vertex, at nearly the same distance from the wish: then the C's velocity still meets
every constraint within ``SAT_TOL`` and is as near the wish as Python's within ``POINT_TOL``) or a row on the
edge between reachable and not (the distance from the own velocity to the safe velocities within the max speed
equals the reachable radius within ``POINT_TOL``, so rounding may pick either branch); such rows must stay rare
(under 0.1%). The figures (max |C - Python| in m/s and the counts) are printed and recorded (``record_property``)."""
from __future__ import annotations

import ctypes
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from firmware_export import cgen, m4_emu
from firmware_export.c_export import STUBS_DIR, TEMPLATE_DIR
from firmware_export.cgen_avoid import AVOID_PREFIX, avoid_defines, c_feasible_tol
from firmware_export.mlp_graph import ActorModel, Dense
from firmware_export.toolchain import APP_WARN_FLAGS, arm_gcc, build_host_library, compile_m4_object
from runtime.avoidance import REACH_SHRINK, avoid_rows, nearest_feasible, role_tables
from runtime.spec import Role, SwarmSpec
from runtime.world import World, action_to_velocity

from test_avoidance import ON, avoidance_cases, constraints, discs, outside, violation, wish

FIRMWARE_FLAGS = ("-Os", "-Wdouble-promotion", "-fno-math-errno")
"""What crazyflie-firmware's Makefile adds for app sources (-Os, -Wdouble-promotion under -Werror)."""
N_CASES = 6000
EVEN = SwarmSpec.from_dict({"avoidance": {"enabled": True, "braking": 2.0, "obstacle_margin": 0.06,
                                          "teammate_margin": 0.12, "teammate_braking": 3.4, "teammate_credit": 0.6},
                            "team": {"n_pursuers": 3, "n_scouts": 0, "n_evaders": 3},
                            "pursuer": {"radius": 0.06, "max_speed": 0.9, "max_accel": 2.5}})
"""Other numbers than the default: another braking, margins, teammate credit, team and pursuer body, so that nothing
in the C holds the defaults by accident."""


EPS32 = float(np.finfo(np.float32).eps)


def tolerances(spec: SwarmSpec, role: Role) -> tuple[float, float]:
    """``SAT_TOL`` and ``POINT_TOL`` [m/s] for ``role`` (see the module docstring)."""
    params, _ = role_tables(spec, role)
    rs = spec.role(role)
    top = rs.max_speed + rs.max_accel * spec.timing.control_period  # the largest velocity in play
    ulp_hw = float(np.spacing(np.float32(spec.arena.half_width)))
    limit_err = 4 * ulp_hw / spec.timing.control_period
    sat = c_feasible_tol(params) + limit_err + 3 * EPS32 * top + EPS32 * rs.max_speed
    return sat, 5.0 * sat


def _model(spec: SwarmSpec, role: Role) -> ActorModel:
    rng = np.random.default_rng(0)
    dims = [spec.obs_dim(role), 8, 2]
    layers = tuple(Dense(rng.normal(0, 0.3, (b, a)).astype(np.float32), np.zeros(b, np.float32), act)
                   for a, b, act in zip(dims, dims[1:], ("relu", "tanh")))
    return ActorModel(layers, spec, role, f"{role.label}_0", "test")


class CAvoid:
    """``swarm_avoid`` of the template's swarm_logic.c, built on the host with the app's and the firmware's flags
    against a policy.h generated for ``spec`` and ``role``."""

    def __init__(self, spec: SwarmSpec, role: Role, work: Path) -> None:
        self.spec, self.role = spec, role
        d = work / f"{role.label}_{spec.hash}"
        d.mkdir(parents=True, exist_ok=True)
        gen = cgen.generate(_model(spec, role))
        self.header = gen.header
        (d / "policy.h").write_text(gen.header)
        (d / "policy.c").write_text(gen.source)
        for name in ("swarm_logic.c", "swarm_logic.h"):
            shutil.copyfile(TEMPLATE_DIR / "src" / name, d / name)
        so = build_host_library([d / "swarm_logic.c"], d / "libavoid.so", (*FIRMWARE_FLAGS, f"-I{d}"),
                                APP_WARN_FLAGS)
        self.lib = ctypes.CDLL(str(so))
        self.lib.swarm_avoid.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self.lib.swarm_avoid.restype = None
        self.dim = spec.obs_dim(role)

    def __call__(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        obs = np.ascontiguousarray(obs, dtype=np.float32)
        out = np.array(act, dtype=np.float32, copy=True, order="C")
        assert obs.shape == (len(out), self.dim)
        for i in range(len(out)):
            self.lib.swarm_avoid(obs[i].ctypes.data, out[i].ctypes.data)
        return out


def _python(spec: SwarmSpec, role: Role, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
    """The runtime's path: float32 observation and action, as OnnxPolicy passes them."""
    out = np.array(act, dtype=np.float32, copy=True)
    params, layout = role_tables(spec, role)
    avoid_rows(np.ascontiguousarray(obs, dtype=np.float32), out, params, layout)
    return out


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("avoid_c")


def _defines(text: str) -> dict[str, str]:
    return dict(re.findall(rf"^#define ({AVOID_PREFIX}_\w+) (\S+)", text, flags=re.M))


# --------------------------------------------------------------------------------------------------
# the generated numbers


@pytest.mark.parametrize("spec, role", [(ON, Role.PURSUER), (ON, Role.SCOUT), (ON, Role.EVADER),
                                        (EVEN, Role.PURSUER), (EVEN, Role.EVADER)],
                         ids=["default-pursuer", "default-scout", "default-evader", "other-pursuer", "other-evader"])
def test_policy_h_holds_the_kernels_tables(spec, role):
    d = _defines("\n".join(avoid_defines(spec, role)))
    params, layout = role_tables(spec, role)
    assert np.float32(d.pop("SWARM_AVOID_REACH_SHRINK")[:-1]) == np.float32(REACH_SHRINK)
    assert np.float32(d.pop("SWARM_AVOID_FEASIBLE_TOL")[:-1]) == np.float32(c_feasible_tol(params))
    floats = [v for k, v in d.items() if v.endswith("f")]
    ints = [v for k, v in d.items() if k not in ("SWARM_AVOID_ENABLED", "SWARM_AVOID_OBSTACLE_COLS",
                                                 "SWARM_AVOID_MATE_COLS") and not v.endswith("f")]
    assert d["SWARM_AVOID_ENABLED"] == "1"
    assert [np.float32(v[:-1]) for v in floats] == list(params.astype(np.float32))  # in the kernel's order
    assert [int(v) for v in ints] == list(layout)
    lay = spec.layout(role)
    assert int(d["SWARM_AVOID_N_MATES"]) == lay["teammates"].rows
    assert float(d["SWARM_AVOID_MAX_SPEED"][:-1]) == pytest.approx(spec.role(role).max_speed)


def test_layer_off_generates_only_the_switch():
    d = _defines("\n".join(avoid_defines(SwarmSpec(), Role.PURSUER)))
    assert d == {"SWARM_AVOID_ENABLED": "0"}
    assert "#define SWARM_AVOID_ENABLED 0" in cgen.generate(_model(SwarmSpec(), Role.PURSUER)).header


# --------------------------------------------------------------------------------------------------
# C against Python


def compare(spec: SwarmSpec, role: Role, obs: np.ndarray, act: np.ndarray, got: np.ndarray,
            want: np.ndarray) -> dict[str, float]:
    """The C's actions ``got`` against Python's ``want`` on float32 ``obs``, ``act`` (module docstring): asserts
    per row and returns the figures."""
    sat, point = tolerances(spec, role)
    vmax = spec.role(role).max_speed
    params, _ = role_tables(spec, role)
    lay = spec.layout(role)
    diff = np.abs(got.astype(np.float64) - want).max(axis=1) * vmax
    ties = edges = 0
    worst_out = -np.inf
    for k in range(len(obs)):
        o = obs[k].astype(np.float64)
        normals, limits, _ = constraints(spec, role, o)
        centres, radii = discs(spec, role, o)
        c, p = got[k].astype(np.float64) * vmax, want[k].astype(np.float64) * vmax
        reach_p = outside(p, centres[1:], radii[1:]) <= 1e-6  # Python's branch (its action is float32 too)
        reach_c = outside(c, centres[1:], radii[1:]) <= sat
        if reach_p != reach_c:  # on the edge between reachable and not?
            own, out = centres[1], np.empty(2)
            nx, ny = np.ascontiguousarray(normals[:, 0]), np.ascontiguousarray(normals[:, 1])
            assert nearest_feasible(own[0], own[1], nx, ny, limits, len(limits), np.zeros(1), np.zeros(1),
                                    radii[:1].copy(), 1, out)  # the safe velocity within max speed nearest own
            slack = radii[1] - np.hypot(*(out - own))
            assert abs(slack) <= point, (k, slack)
            edges += 1
            continue
        used = slice(None) if reach_p else slice(0, 1)
        worst = max(violation(c, normals, limits), outside(c, centres[used], radii[used]))
        worst_out = max(worst_out, worst)
        assert worst <= sat, (k, worst)
        if diff[k] > point:  # a near-tie: as near the wish as Python's answer
            w = wish(spec, role, act[k])
            assert abs(np.hypot(*(c - w)) - np.hypot(*(p - w))) <= point, k
            ties += 1
    assert ties + edges <= 1e-3 * len(obs)
    return {"max_abs_diff_m_s": float(diff.max()), "worst_outside_m_s": float(worst_out), "near_ties": ties,
            "edges": edges, "sat_tol": sat, "point_tol": point}


@pytest.mark.parametrize("spec", [ON, EVEN], ids=["default", "other"])
@pytest.mark.parametrize("role", [Role.PURSUER, Role.EVADER])
def test_c_matches_the_python_kernel_on_random_observations(work, spec, role, record_property):
    c = CAvoid(spec, role, work)
    obs, act = avoidance_cases(spec, role, N_CASES, seed=20 + int(role))
    want = _python(spec, role, obs, act)
    got = c(obs, act)
    changed = (want != act).any(axis=1)
    figures = compare(spec, role, obs, act, got, want)
    print(f"{role.label}: max |C - Python| {figures['max_abs_diff_m_s']:.3g} m/s (tolerance "
          f"{figures['point_tol']:.2g}), worst excess over a constraint {figures['worst_outside_m_s']:.2g} m/s "
          f"(tolerance {figures['sat_tol']:.2g}), {figures['near_ties']} near-ties, {figures['edges']} edge rows; "
          f"{changed.sum()} of {N_CASES} changed by the layer")
    for name, value in figures.items():
        record_property(f"{name}_{role.label}", value)
    assert changed.mean() > 0.3  # the layer was at work, not idle
    # what the layer leaves alone, the C leaves alone to the bit
    np.testing.assert_array_equal(got[~changed], act[~changed])


def test_c_leaves_the_action_alone_on_non_finite_input(work):
    c = CAvoid(ON, Role.PURSUER, work)
    obs, act = avoidance_cases(ON, Role.PURSUER, 40, seed=30)
    act[:, 0] = 1.0  # every row pressed into its speed limit and more, so the layer would change it
    act[:, 1] = 1.0
    obs[::2, 7] = np.nan
    obs[1::4, 0] = np.inf
    bad_obs = ~np.isfinite(obs).all(axis=1)
    np.testing.assert_array_equal(c(obs, act)[bad_obs], act[bad_obs])
    np.testing.assert_array_equal(_python(ON, Role.PURSUER, obs, act)[bad_obs], act[bad_obs])
    nan_act = act[~bad_obs].copy()
    nan_act[:, 1] = np.nan  # a broken network: swarm_action_to_velocity turns it into a stop
    np.testing.assert_array_equal(c(obs[~bad_obs], nan_act), nan_act)


@pytest.mark.parametrize("role", [Role.PURSUER, Role.EVADER])
def test_c_is_the_identity_with_the_layer_off(work, role):
    off = SwarmSpec()
    c = CAvoid(off, role, work)
    obs, act = avoidance_cases(ON, role, 2000, seed=31)  # the same hazards; norms up to sqrt(2) included
    np.testing.assert_array_equal(c(obs, act), act)
    assert (_python(ON, role, obs, act) != act).any()  # where the layer, on, would have acted


def _runtime_velocity(spec: SwarmSpec, role: Role, act: np.ndarray) -> np.ndarray:
    """What the Python runtime commands for actions ``[B, 2]`` of ``role``: ``World.sanitize_actions`` (a
    non-finite action is a stop, clipped to [-1, 1]) and ``action_to_velocity``."""
    world = World(spec, n_envs=len(act))
    rows = np.zeros((len(act), spec.n_agents, 2))
    rows[:, 0] = act
    return action_to_velocity(np.array([spec.role(role).max_speed]), world.sanitize_actions(rows)[:, 0])


@pytest.mark.parametrize("spec", [ON, SwarmSpec()], ids=["layer-on", "layer-off"])
def test_app_action_to_velocity_is_the_runtimes(work, spec):
    """swarm_action_to_velocity against runtime.world (sanitize_actions, action_to_velocity) on actions in and
    beyond [-1, 1]^2, NaN and inf included, at positions across the arena and at its walls. With the layer on they
    agree everywhere (the layer is the wall rule on both sides); with it off the app adds its stop towards a wall
    within SWARM_WALL_MARGIN (the runtime's commands pass the ground station's geofence, the app's do not), and
    agrees everywhere else."""
    c = CAvoid(spec, Role.PURSUER, work)
    fn = c.lib.swarm_action_to_velocity
    fn.argtypes = [ctypes.c_void_p, ctypes.c_float, ctypes.c_float, ctypes.c_void_p]
    fn.restype = None
    rng = np.random.default_rng(50)
    n, hw = 3000, spec.arena.half_width
    act = rng.uniform(-1.6, 1.6, (n, 2)).astype(np.float32)
    act[rng.random(n) < 0.03, 0] = np.nan
    act[rng.random(n) < 0.03, 1] = np.inf
    act[rng.random(n) < 0.03, 0] = -np.inf
    pos = rng.uniform(-hw, hw, (n, 2)).astype(np.float32)
    at_wall = rng.random(n) < 0.3
    pos[at_wall, 0] = np.sign(pos[at_wall, 0]) * rng.uniform(hw - 0.2, hw, int(at_wall.sum()))
    got = np.zeros((n, 2), np.float32)
    for k in range(n):
        fn(act[k].ctypes.data, float(pos[k, 0]), float(pos[k, 1]), got[k].ctypes.data)
    want = _runtime_velocity(spec, Role.PURSUER, act.astype(np.float64))
    same = np.abs(got - want).max(axis=1) <= 2 * EPS32 * spec.pursuer.max_speed
    if spec.avoidance.enabled:
        assert same.all(), np.nonzero(~same)[0][:5]
    else:
        lim = hw - 0.15  # SWARM_WALL_MARGIN
        stop = (((pos >= lim) & (want > 0)) | ((pos <= -lim) & (want < 0))).any(axis=1)
        assert same[~stop].all() and not same[stop & (np.abs(want) > 1e-3).all(axis=1)].any()
        assert 100 < stop.sum() < n // 2
    assert (~np.isfinite(act)).any(axis=1).sum() > 150 and np.isfinite(got).all()


# --------------------------------------------------------------------------------------------------
# the app


def _run_towards_plus_x(run_dir: Path, spec: SwarmSpec) -> Path:
    """A run whose actors fly at nearly full speed towards +x whatever they see (random hidden layers, an output
    layer of tiny weights and a bias of (2.5, 0)): the app test flies one into the +x wall."""
    torch = pytest.importorskip("torch")
    from training.checkpoint import save_actors
    from training.networks import Actor

    torch.manual_seed(4)
    actors = [Actor(spec.obs_dim(r)) for r in spec.roles]
    with torch.no_grad():
        for a in actors:
            a.net[-2].weight.mul_(0.01)
            a.net[-2].bias.copy_(torch.tensor([2.5, 0.0]))
    save_actors(run_dir / "actors.pt", spec, actors, config={"note": "test actors flying towards +x"},
                meta={"evaluation": {"tracking_rate": 0.0}})
    return run_dir


def _export_app(tmp: Path, spec: SwarmSpec) -> Path:
    """``swarm-export c --app`` of an actor exported by ``swarm-export onnx`` from a run of ``spec``."""
    from firmware_export.cli import main
    from firmware_export.onnx_export import export_run

    models = tmp / "models"
    export_run(_run_towards_plus_x(tmp / "run", spec), models, n_random=200, n_recorded=200)
    app = tmp / "app"
    assert main(["c", "--model", str(models / "pursuer_0.onnx"), "--out", str(tmp / "c"), "--app", str(app)]) == 0
    return app


@pytest.fixture(scope="module")
def app_on(tmp_path_factory) -> Path:
    return _export_app(tmp_path_factory.mktemp("app_on"), ON)


class _Record(ctypes.Structure):
    _fields_ = [("ms", ctypes.c_uint32), ("priority", ctypes.c_int), ("vx", ctypes.c_float), ("vy", ctypes.c_float),
                ("z", ctypes.c_float), ("mode_x", ctypes.c_int), ("mode_y", ctypes.c_int), ("mode_z", ctypes.c_int)]


class _Var(ctypes.Structure):
    _fields_ = [("type", ctypes.c_int), ("name", ctypes.c_char_p), ("address", ctypes.c_void_p)]


def _table(lib, name: str) -> dict[str, int]:
    """The stubs' PARAM_ADD / LOG_ADD table: name -> address."""
    out = {}
    for v in (_Var * 64).in_dll(lib, name):
        if not v.name:
            break
        out[v.name.decode()] = v.address
    return out


def test_exported_app_with_the_layer_on_builds_and_its_setpoints_pass_the_layer(app_on, tmp_path):
    """The whole app (shell, logic, generated policy) on the host against the firmware stubs: a pursuer flying at
    1 m/s into the +x wall is slowed by the layer, every setpoint is the layer's output of the logged raw action
    and the observation (own velocity included) through the runtime's action_to_velocity, and it never enters
    the wall's margin at more than the barrier allows."""
    src = app_on / "src"
    header = (src / "policy.h").read_text()
    assert "#define SWARM_AVOID_ENABLED 1" in header
    so = build_host_library([src / "swarm_app.c", src / "swarm_logic.c", src / "policy.c",
                             STUBS_DIR / "crazyflie_host.c"], tmp_path / "libapp.so",
                            ("-O2", f"-I{src}", f"-I{STUBS_DIR / 'include'}", "-Wdouble-promotion"), APP_WARN_FLAGS)
    lib = ctypes.CDLL(str(so))
    params, logs = _table(lib, "stub_param_swarm"), _table(lib, "stub_log_swarm")
    ctypes.c_uint8.from_address(params["agent"]).value = 0
    ctypes.c_uint8.from_address(params["enable"]).value = 1
    ctypes.c_uint8.from_address(params["nObst"]).value = 0
    state = (ctypes.c_float * 4).in_dll(lib, "stub_state")
    heartbeat = ctypes.c_uint16.from_address(params["heartbeat"])
    hw = ON.arena.half_width
    xs = np.linspace(hw - 0.6, hw - 0.075, 30)
    seen = []

    @ctypes.CFUNCTYPE(None, ctypes.c_uint32)
    def step(now_ms):
        k = min(now_ms // 100 - 1, len(xs) - 1)
        state[0], state[1], state[2], state[3] = float(xs[k]), 0.0, 1.0, 0.0
        heartbeat.value = now_ms // 100
        seen.append((now_ms, ctypes.c_float.from_address(logs["act0"]).value,
                     ctypes.c_float.from_address(logs["act1"]).value))

    lib.stub_run_app.argtypes = [ctypes.c_uint32, type(step)]
    n = lib.stub_run_app(len(xs) * 100, step)
    recs = [r for r in (_Record * 4096).in_dll(lib, "stub_records")[:n] if r.priority == 2]
    assert len(recs) >= len(xs) - 2
    # the logged act0/act1 of period k are read at the start of period k+1 (the step callback runs first)
    raw = {ms - 100: (a0, a1) for ms, a0, a1 in seen}
    lay = ON.layout(Role.PURSUER)
    params_py, layout_py = role_tables(ON, Role.PURSUER)
    slowed = 0
    for r in recs:
        if r.ms not in raw:
            continue
        x = np.float32(xs[min(r.ms // 100 - 1, len(xs) - 1)])
        obs = np.zeros((1, lay.dim), np.float32)
        obs[0, :4] = (x, 0.0, 1.0, 0.0)
        act = np.array([raw[r.ms]], np.float32)
        avoid_rows(obs, act, params_py, layout_py)
        # no teammate heard, no obstacle set: walls only, so the observation above is the app's; then
        # swarm_action_to_velocity, the runtime's action_to_velocity (no second wall rule with the layer on)
        vel = action_to_velocity(np.array([ON.pursuer.max_speed]), act.astype(np.float64))[0]
        assert abs(r.vx - vel[0]) <= 1e-4 and abs(r.vy - vel[1]) <= 1e-4
        gap = hw - ON.pursuer.radius - float(x) - ON.avoidance.obstacle_margin
        assert r.vx <= max(0.0, min(np.sqrt(2 * ON.avoidance.braking * max(gap, 0)), gap / 0.1)) + 1e-4
        slowed += raw[r.ms][0] > 0 and r.vx < raw[r.ms][0] - 1e-3
    assert slowed >= 5


@pytest.mark.skipif(arm_gcc() is None, reason="arm-none-eabi-gcc not installed (apt-get install gcc-arm-none-eabi)")
def test_exported_app_with_the_layer_on_compiles_for_cortex_m4(app_on, tmp_path):
    src = app_on / "src"
    for name in ("swarm_app.c", "swarm_logic.c", "policy.c"):
        compile_m4_object(src / name, tmp_path / f"{name}.o", include=(src, STUBS_DIR / "include"),
                          opt=("-Os",), warn=(*APP_WARN_FLAGS, "-Wdouble-promotion"))


M4_WRAPPER = """/* swarm_avoid behind the emulator's entry point: the buffer holds the observation, then the action. */
#include "swarm_logic.c"
void swarm_policy_init(void) {}
void swarm_policy_act(const float obs[SWARM_POLICY_OBS_DIM], float act[SWARM_POLICY_ACT_DIM])
{
    const float *tail = (const float *)((uintptr_t)obs + sizeof(float) * SWARM_POLICY_OBS_DIM);
    act[0] = tail[0];
    act[1] = tail[1];
    swarm_avoid(obs, act);
}
"""


def _costly_rows(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pursuer rows with every teammate slot valid and every obstacle slot used (all 11 constraints and both
    discs in play), the wish outside them; ``reach`` tells which rows have a safe reachable velocity (the others
    run the enumeration twice: with and without the reachability disc)."""
    obs, act = avoidance_cases(ON, Role.PURSUER, 40 * n, seed=seed)
    lay = ON.layout(Role.PURSUER)
    tm, ob = lay["teammates"], lay["obstacles"]
    obs[:, tm.start + 4:tm.start + tm.size:5] = 1.0
    obs[:, ob.start + 2:ob.start + ob.size:3] = np.maximum(obs[:, ob.start + 2:ob.start + ob.size:3], 0.25)
    want = _python(ON, Role.PURSUER, obs, act)
    reach = np.array([outside(w.astype(np.float64), *(x[1:] for x in discs(ON, Role.PURSUER, o))) <= 1e-6
                      for o, w in zip(obs, want)])
    moved = (want != act).any(axis=1)
    rows = np.r_[np.nonzero(moved & reach)[0][:n], np.nonzero(moved & ~reach)[0][:n]]
    assert len(rows) == 2 * n
    return obs[rows], act[rows], reach[rows]


@pytest.mark.skipif(arm_gcc() is None, reason="arm-none-eabi-gcc not installed (apt-get install gcc-arm-none-eabi)")
def test_swarm_avoid_on_the_cortex_m4_matches_python_and_costs_under_250_us(work, record_property):
    """Built as the firmware builds app sources (-Os, -fno-math-errno: VSQRT inline) and run in the emulator
    (firmware_export.m4_emu: the Cortex-M4 TRM's cycle counts at 168 MHz) on the costliest rows: all 11
    constraints and both discs in play, the wish outside them; half the rows without a safe reachable velocity
    (the enumeration runs twice)."""
    pytest.importorskip("unicorn", reason="unicorn not installed (pip install unicorn); no M4 emulation")
    c = CAvoid(ON, Role.PURSUER, work)  # writes policy.h and swarm_logic.c
    d = work / f"pursuer_{ON.hash}"
    (d / "m4_avoid.c").write_text(M4_WRAPPER)
    obj = compile_m4_object(d / "m4_avoid.c", d / "m4_avoid.o", include=(d,), opt=("-Os", "-fno-math-errno"),
                            warn=(*APP_WARN_FLAGS, "-Wdouble-promotion"))
    build = m4_emu.build_from_object(obj, d / "m4")
    obs, act, reach = _costly_rows(8, seed=40)
    want = _python(ON, Role.PURSUER, obs, act)
    runs = [m4_emu.run(build, np.r_[o, a]) for o, a in zip(obs, act)]
    got = np.array([r.act for r in runs], np.float32)
    # the M4 build is the host build but for rounding (the M4 fuses multiply-adds: VFMA)
    np.testing.assert_allclose(got, c(obs, act), rtol=0, atol=tolerances(ON, Role.PURSUER)[1])
    us = np.array([m4_emu.micros(r.total_cycles) for r in runs])
    cycles = max(r.total_cycles for r in runs)
    figures = compare(ON, Role.PURSUER, obs, act, got, want)
    print(f"swarm_avoid on the M4: reachable rows median {np.median(us[reach]):.1f} us max {us[reach].max():.1f} us; "
          f"unreachable rows (two passes) median {np.median(us[~reach]):.1f} us max {us[~reach].max():.1f} us "
          f"({cycles} cycles at most); max |M4 - Python| {figures['max_abs_diff_m_s']:.3g} m/s")
    record_property("m4_swarm_avoid_max_us", float(us.max()))
    record_property("m4_swarm_avoid_median_us_reachable", float(np.median(us[reach])))
    record_property("m4_swarm_avoid_median_us_unreachable", float(np.median(us[~reach])))
    assert us.max() <= 250.0  # measured 175 us (29,440 cycles at 168 MHz); the network itself takes 161 us
