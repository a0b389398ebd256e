"""The avoidance layer's numbers for ``policy.h``: the C twin of ``runtime.avoidance`` reads them.

Every value comes from ``runtime.avoidance.role_tables(spec, role)``, the arrays the Python kernel ``avoid_rows``
runs on, and is named after the kernel's index constants (``P_OWN_RADIUS`` -> ``SWARM_AVOID_OWN_RADIUS``,
``L_N_MATES`` -> ``SWARM_AVOID_N_MATES``): nothing is computed twice, and a parameter the kernel gains without a
C twin is an export error here instead of a silent difference on the drone. Two tolerances come with them:
``REACH_SHRINK`` as the kernel's, and the feasibility slack, ``FEASIBLE_TOL``'s float32 equivalent
(``c_feasible_tol``, argued there). ``swarm_avoid`` in the app's ``swarm_logic.c`` is the function; with the
spec's layer off only ``SWARM_AVOID_ENABLED 0`` is generated and ``swarm_avoid`` compiles to nothing.
"""
from __future__ import annotations

import numpy as np

from runtime import avoidance
from runtime.spec import Role, SwarmSpec

from firmware_export.mlp_graph import CExportError

AVOID_PREFIX = "SWARM_AVOID"

_DOCS = {
    "OWN_RADIUS": "[m] this role's body radius",
    "MATE_RADIUS": "[m] a teammate's body radius (the largest of the roles its slots can hold)",
    "MAX_SPEED": "[m/s] the velocity of an action of norm 1",
    "MAX_ACCEL": "[m/s^2] this role's acceleration limit (the reachability disc)",
    "HALF_WIDTH": "[m] walls at +-HALF_WIDTH",
    "DT": "[s] control period",
    "BRAKING": "[m/s^2] deceleration the barrier plans with",
    "OBS_MARGIN": "[m] gap to an obstacle's or a wall's surface where the approach speed reaches zero",
    "MATE_MARGIN": "[m] gap between two teammates' bodies where the approach speed reaches zero",
    "MATE_BRAKING": "[m/s^2] relative deceleration the teammate barrier plans with (each teammate takes half)",
    "MATE_CREDIT": "share of a teammate's own speed away added to the approach budget toward it",
    "SELF_POS": "observation index of the own x (y follows)",
    "SELF_VEL": "observation index of the own vx (vy follows)",
    "OBSTACLES": "observation index of the first obstacle slot (dx, dy, radius; radius 0: empty)",
    "N_OBSTACLES": "obstacle slots",
    "MATES": "observation index of the first teammate slot (dx, dy, vx, vy, valid)",
    "N_MATES": "teammate slots",
}


C_FEASIBLE_TOL_ULPS = 64
"""``swarm_avoid``'s feasibility slack in float32 epsilons of the largest velocity in play (``c_feasible_tol``)."""


def c_feasible_tol(params: np.ndarray) -> float:
    """The float32 twin of ``runtime.avoidance.FEASIBLE_TOL`` [m/s] for a role's kernel ``params``: the slack with
    which ``swarm_avoid`` accepts a candidate.

    It must cover what float32 rounding leaves of a candidate's residual on its own active constraints, else the
    exact optimum is rejected and a farther candidate wins (the float64 kernel did exactly that while it rounded
    its normals to float32). Only candidates within the speed disc can pass, so the numbers in a residual are of
    size at most ``S = max_speed + max_accel x control_period`` (a velocity, a line's offset where it passes
    near one, a disc's centre plus radius). A normal computed in float has ``|n|^2 = 1 +- 3 eps``, which a
    projection of length ``<= 2 S`` turns into ``6 eps S``; the dot product and the offset add 3 to 4 roundings
    of size ``S``; an intersection's 2 x 2 solve or a circle's square root a few more: about ``16 eps S`` at
    worst. ``64 eps S`` is four times that: 9.9e-6 m/s for the default pursuer, 1.3e-5 m/s for the evader; a
    velocity beyond a barrier's limit by that much covers 1 um more in a control period. Measured on 24,000
    random rows (tests/test_avoidance_c.py): ``4 eps S`` already reproduces the float64 kernel's choices,
    ``1 eps S`` does not (1 row in 500 up to 1.2 m/s away)."""
    scale = params[avoidance.P_MAX_SPEED] + params[avoidance.P_MAX_ACCEL] * params[avoidance.P_DT]
    return max(avoidance.FEASIBLE_TOL, C_FEASIBLE_TOL_ULPS * float(np.finfo(np.float32).eps) * float(scale))


def _names(prefix: str) -> list[tuple[int, str]]:
    """(index, name) of the kernel's ``P_*`` or ``L_*`` constants, in index order."""
    return sorted((v, k[len(prefix):]) for k, v in vars(avoidance).items()
                  if k.startswith(prefix) and k[len(prefix):].isupper() and isinstance(v, int))


def avoid_defines(spec: SwarmSpec, role: Role) -> list[str]:
    """``#define`` lines for ``policy.h`` (``c_float`` literals, so the C reads the float32 of each value)."""
    from firmware_export.cgen import c_float

    if not spec.avoidance.enabled:
        return ["/* Avoidance layer (runtime.avoidance): off in this spec; swarm_avoid leaves the action as it is. */",
                f"#define {AVOID_PREFIX}_ENABLED 0"]
    params, layout = avoidance.role_tables(spec, role)
    pnames, lnames = _names("P_"), _names("L_")
    if [i for i, _ in pnames] != list(range(len(params))) or [i for i, _ in lnames] != list(range(len(layout))):
        raise CExportError(f"runtime.avoidance names {len(pnames)} params and {len(lnames)} layout entries, its "
                           f"tables hold {len(params)} and {len(layout)}: update firmware_export/cgen_avoid.py "
                           "and swarm_avoid in the app with the kernel")
    missing = [n for _, n in pnames + lnames if n not in _DOCS]
    if missing:
        raise CExportError(f"runtime.avoidance has entries {missing} that the C app does not know: add them to "
                           "firmware_export/cgen_avoid.py and to swarm_avoid in the app's swarm_logic.c")
    ob = spec.layout(role)["obstacles"]
    if ob.columns != ("dx", "dy", "radius"):
        raise CExportError(f"the obstacles field's columns are {ob.columns}, swarm_avoid reads (dx, dy, radius): "
                           "update it and runtime.avoidance together")
    lines = [f"/* Avoidance layer (runtime.avoidance, spec.avoidance; the C twin is swarm_avoid in swarm_logic.c),",
             f" * {Role(role).label}: runtime.avoidance.role_tables. */",
             f"#define {AVOID_PREFIX}_ENABLED 1"]
    lines += [f"#define {AVOID_PREFIX}_{n} {c_float(params[i])} /* {_DOCS[n]} */" for i, n in pnames]
    lines += [f"#define {AVOID_PREFIX}_{n} {int(layout[i])} /* {_DOCS[n]} */" for i, n in lnames]
    lines += [f"#define {AVOID_PREFIX}_FEASIBLE_TOL {c_float(c_feasible_tol(params))} /* [m/s] a candidate's slack "
              "in float32 (runtime.avoidance.FEASIBLE_TOL is float64's): firmware_export.cgen_avoid.c_feasible_tol */",
              f"#define {AVOID_PREFIX}_REACH_SHRINK {c_float(avoidance.REACH_SHRINK)} /* the reachability disc's "
              "radius is MAX_ACCEL x DT x (1 - REACH_SHRINK): runtime.avoidance.REACH_SHRINK */",
              f"#define {AVOID_PREFIX}_OBSTACLE_COLS {len(ob.columns)}",
              f"#define {AVOID_PREFIX}_MATE_COLS {avoidance.MATE_COLUMNS} /* dx, dy, vx, vy, valid */"]
    return lines
