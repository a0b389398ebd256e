"""The avoidance layer's numbers for ``policy.h``: the C twin of ``runtime.avoidance`` reads them.

Every value comes from ``runtime.avoidance.role_tables(spec, role)``, the arrays the Python kernel ``avoid_rows``
runs on, and is named after the kernel's index constants (``P_OWN_RADIUS`` -> ``SWARM_AVOID_OWN_RADIUS``,
``L_N_MATES`` -> ``SWARM_AVOID_N_MATES``): nothing is computed twice, and a parameter the kernel gains without a
C twin is an export error here instead of a silent difference on the drone. ``swarm_avoid`` in the app's
``swarm_logic.c`` is the function; with the spec's layer off only ``SWARM_AVOID_ENABLED 0`` is generated and
``swarm_avoid`` compiles to nothing.
"""
from __future__ import annotations

from runtime import avoidance
from runtime.spec import Role, SwarmSpec

from firmware_export.mlp_graph import CExportError

AVOID_PREFIX = "SWARM_AVOID"

_DOCS = {
    "OWN_RADIUS": "[m] this role's body radius",
    "MATE_RADIUS": "[m] a teammate's body radius (the largest of the roles its slots can hold)",
    "MAX_SPEED": "[m/s] the velocity of an action of norm 1",
    "HALF_WIDTH": "[m] walls at +-HALF_WIDTH",
    "DT": "[s] control period",
    "BRAKING": "[m/s^2] deceleration the barrier plans with",
    "OBS_MARGIN": "[m] gap to an obstacle's or a wall's surface where the approach speed reaches zero",
    "MATE_MARGIN": "[m] gap between two teammates' bodies where the approach speed reaches zero",
    "SELF_POS": "observation index of the own x (y follows)",
    "OBSTACLES": "observation index of the first obstacle slot (dx, dy, radius; radius 0: empty)",
    "N_OBSTACLES": "obstacle slots",
    "MATES": "observation index of the first teammate slot (dx, dy, vx, vy, valid)",
    "N_MATES": "teammate slots",
    "ROUNDS": "passes of the cyclic projection",
}


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
    lines += [f"#define {AVOID_PREFIX}_OBSTACLE_COLS {len(ob.columns)}",
              f"#define {AVOID_PREFIX}_MATE_COLS {avoidance.MATE_COLUMNS} /* dx, dy, vx, vy, valid */"]
    return lines
