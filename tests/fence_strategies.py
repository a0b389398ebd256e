"""Hypothesis strategies for geofences and points (``test_safety``, ``test_fence_geometry``)."""
from __future__ import annotations

import math

from hypothesis import assume
from hypothesis import strategies as st

from groundstation.safety import FenceConfig, KeepOut
from runtime.spec import SpecError

any_float = st.one_of(
    st.floats(-5.0, 5.0),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e308, -1e308, 1e-308, math.nan, math.inf, -math.inf]),
)
point = st.tuples(any_float, any_float, any_float)
sane = st.floats(-4.0, 4.0)
sane_point = st.tuples(sane, sane, st.floats(-0.5, 3.0))


@st.composite
def fences(draw: st.DrawFn) -> FenceConfig:
    if draw(st.booleans()):
        x0 = draw(st.floats(-4, 0)); y0 = draw(st.floats(-4, 0))
        shape = {"box": (x0, x0 + draw(st.floats(1.5, 7)), y0, y0 + draw(st.floats(1.5, 7)))}
    else:  # a convex polygon: corners on an ellipse at sorted angles
        n = draw(st.integers(3, 8))
        ang = sorted(draw(st.lists(st.floats(0, 2 * math.pi, exclude_max=True), min_size=n, max_size=n,
                                   unique=True)))
        assume(all(b - a > 0.3 for a, b in zip(ang, ang[1:] + [ang[0] + 2 * math.pi])))
        ax, ay = draw(st.floats(1.5, 4)), draw(st.floats(1.5, 4))
        verts = tuple((ax * math.cos(a), ay * math.sin(a)) for a in ang)
        shape = {"vertices": verts if draw(st.booleans()) else verts[::-1]}
    keep = tuple(KeepOut(draw(st.floats(-3, 3)), draw(st.floats(-3, 3)), draw(st.floats(0.05, 0.8)))
                 for _ in range(draw(st.integers(0, 4))))
    try:
        return FenceConfig(**shape, keep_out=keep, margin=draw(st.floats(0.0, 0.4)),
                           z_min=draw(st.floats(0.0, 0.5)), z_max=draw(st.floats(1.5, 3.0)),
                           max_speed=draw(st.floats(0.2, 3.0)), max_decel=draw(st.floats(0.5, 5.0)),
                           coast_time=draw(st.sampled_from([2.0, 0.5, 3.0, 1e-3])))
    except SpecError:
        assume(False)
        raise
