"""Vectorisable float32 arctan, arctan2, arccos, sin, cos and tan for the planner.

XLA:CPU evaluates `atan2`, `atan`, `acos`, `sin`, `cos` and `tan` by calling scalar
library routines, 6 to 17 ns per element on this project's CPU, against about
1 ns for the polynomials below, which compile to plain vector arithmetic. The
bicycle model (services.plant.dynamics) calls about 25 of them per evaluation,
nine evaluations per rollout step: they were three quarters of the rollout
time (docs/benchmarks.md). `FAST` is a drop-in for `jax.numpy` as the model's
`xp` argument: the same functions, these six replaced (the running time cost's
goal distances, costs.time_cost, use them too). Each is jitted, so a
trace calls it instead of inlining its thirty-odd operations at every use
(about 225 uses per rollout step): tracing and lowering the solver took 7 s
with them inlined and 2 s as calls; XLA inlines the calls when it compiles, so
the program and its results are the same, bit for bit.

Accuracy (tests/test_fastmath.py, against NumPy float64): arctan within 2.5e-7
and arctan2 within 3e-7 absolute everywhere (XLA's own arctan2: 2.5e-7, about
one float32 step at pi), arccos within 3e-7 on [-1, 1], sin and cos within 5e-7 absolute for
|x| <= 1000 rad, tan within 1e-6 relative for |x| <= 1.4 (steering angles are
below 0.6). The classical Cephes single-precision reductions and polynomials.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

_PI = np.float32(np.pi)
_PI_2 = np.float32(np.pi / 2)
_PI_4 = np.float32(np.pi / 4)
_TAN_3PI_8 = np.float32(2.414213562373095)
_TAN_PI_8 = np.float32(0.4142135623730950)
# pi/2 in three float32 parts (Cody-Waite): x - k pi/2 stays exact for |k| < 2**12
_DP1, _DP2, _DP3 = (np.float32(1.5703125), np.float32(4.837512969970703125e-4),
                    np.float32(7.54978995489188216e-8))


def _atan_nonneg(t: Any) -> Any:
    """atan(t) for t >= 0 (Cephes atanf): reduce to |z| <= tan(pi/8), odd polynomial."""
    big = t > _TAN_3PI_8
    mid = (t > _TAN_PI_8) & ~big
    safe = jnp.where(big, t, 1.0)
    z = jnp.where(big, -1.0 / safe, jnp.where(mid, (t - 1.0) / (t + 1.0), t))
    base = jnp.where(big, _PI_2, jnp.where(mid, _PI_4, 0.0))
    z2 = z * z
    p = ((((8.05374449538e-2 * z2 - 1.38776856032e-1) * z2 + 1.99777106478e-1) * z2
          - 3.33329491539e-1) * z2 * z + z)
    return base + p


@jax.jit
def arctan(x: Any) -> Any:
    x = jnp.asarray(x)
    return jnp.copysign(_atan_nonneg(jnp.abs(x)), x)


@jax.jit
def arctan2(y: Any, x: Any) -> Any:
    """atan2 with NumPy's conventions for signed zeros and x < 0 (not for inf or nan)."""
    y, x = jnp.asarray(y), jnp.asarray(x)
    ax, ay = jnp.abs(x), jnp.abs(y)
    swap = ay > ax
    num = jnp.where(swap, ax, ay)
    den = jnp.where(swap, ay, ax)
    a = _atan_nonneg(num / jnp.where(den > 0, den, 1.0))      # in [0, pi/4]
    a = jnp.where(swap, _PI_2 - a, a)
    a = jnp.where(jnp.signbit(x), _PI - a, a)
    return jnp.copysign(a, y)


@jax.jit
def arccos(x: Any) -> Any:
    """arccos on [-1, 1] as arctan2(sqrt((1 - x)(1 + x)), x): (1 - x) is exact near 1, so
    no precision is lost where the slope is steep. Outside [-1, 1] it returns 0 or pi,
    not NaN: callers clip."""
    x = jnp.asarray(x)
    return arctan2(jnp.sqrt(jnp.maximum((1.0 - x) * (1.0 + x), 0.0)), x)


def _reduce(x: Any) -> tuple[Any, Any]:
    """x = k pi/2 + r, |r| <= pi/4; returns (r, k mod 4)."""
    k = jnp.round(x * np.float32(2.0 / np.pi))
    r = ((x - k * _DP1) - k * _DP2) - k * _DP3
    return r, k.astype(jnp.int32) & 3


def _sin_cos_reduced(r: Any) -> tuple[Any, Any]:
    z = r * r
    s = r + r * z * ((-1.9515295891e-4 * z + 8.3321608736e-3) * z - 1.6666654611e-1)
    c = 1.0 - 0.5 * z + z * z * ((2.443315711809948e-5 * z - 1.388731625493765e-3) * z
                                 + 4.166664568298827e-2)
    return s, c


@jax.jit
def sin(x: Any) -> Any:
    r, q = _reduce(jnp.asarray(x))
    s, c = _sin_cos_reduced(r)
    v = jnp.where((q & 1) == 1, c, s)
    return jnp.where(q >= 2, -v, v)


@jax.jit
def cos(x: Any) -> Any:
    r, q = _reduce(jnp.asarray(x))
    s, c = _sin_cos_reduced(r)
    v = jnp.where((q & 1) == 1, s, c)
    return jnp.where((q == 1) | (q == 2), -v, v)


@jax.jit
def tan(x: Any) -> Any:
    r, q = _reduce(jnp.asarray(x))
    s, c = _sin_cos_reduced(r)
    odd = (q & 1) == 1
    return jnp.where(odd, -c, s) / jnp.where(odd, s, c)


class _FastNumpy:
    """`jax.numpy` with the six functions above in place of XLA's scalar ones."""

    arctan = staticmethod(arctan)
    arctan2 = staticmethod(arctan2)
    arccos = staticmethod(arccos)
    sin = staticmethod(sin)
    cos = staticmethod(cos)
    tan = staticmethod(tan)

    def __getattr__(self, name: str) -> Any:
        return getattr(jnp, name)


FAST = _FastNumpy()

