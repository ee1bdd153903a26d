"""One-dimensional prior distributions declared in the configuration.

A prior is written in the config as a small mapping whose ``dist`` key names the family::

    {dist: uniform, low: 0.9, high: 1.3}                       # U(low, high)
    {dist: normal, mean: 2.0, std: 0.1, low: 1.1, high: 2.9}   # N(mean, std), truncated
    {dist: normal, mean: 0.8, std: 0.15, low: 0.0}             # one-sided truncation
    {dist: uniform_int, low: 0, high: 3000}                    # U{low, ..., high}, inclusive
    {dist: power_law, slope: -1.9, low: 1.0e7, high: 1.0e10}   # p(x) ∝ x^slope on [low, high]
    {dist: fixed, value: 0.0}                                  # always ``value``

A bare number is shorthand for ``{dist: fixed, value: <number>}``.

:meth:`Prior.from_config` checks the mapping and raises :class:`PriorError` naming the
config key (e.g. ``scenes.train.main_lens.theta_e.low``), the offending value and what
is allowed. Every family samples exactly and in constant time per draw (inverse CDF, the
truncated normal's by :func:`truncated_normal_quantile`; never a rejection loop) and
draws its randomness only from the ``numpy.random.Generator`` passed to
:meth:`Prior.sample`. Samples are float64
(integers from ``uniform_int`` are exact in float64; cast with ``astype(np.int64)``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from scipy import special

__all__ = [
    "truncated_normal_quantile",
    "PriorError",
    "Prior",
    "Uniform",
    "Normal",
    "UniformInt",
    "PowerLaw",
    "Fixed",
    "DISTRIBUTIONS",
    "JointNormal",
]


def truncated_normal_quantile(u, a, b) -> np.ndarray:
    """Quantile at probability ``u`` of the standard normal truncated to ``[a, b]``.

    ``x = Φ⁻¹(Φ(a) + u (Φ(b) − Φ(a)))``, evaluated on the side of zero where the interval
    lies (an interval with ``a > 0`` is mirrored to ``[−b, −a]``), so that Φ is taken
    in its lower tail, where it keeps full relative precision: agrees with
    ``scipy.stats.truncnorm.ppf`` to ~1e-12 inside, ~1e-7 in the far tails, at ~1/20 of its
    cost per call (which matters for the thousands of small per-image draws of a shard).
    Intervals so far out that Φ underflows (|a|, |b| ≳ 37) go to scipy. Arrays broadcast
    (Φ is evaluated at the shape of the bounds, so one interval for many ``u`` costs two
    Φ calls); the result is clipped to ``[a, b]``.
    """
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    flip = a > 0
    lo, hi = np.where(flip, -b, a), np.where(flip, -a, b)
    p_lo, p_hi = special.ndtr(lo), special.ndtr(hi)  # at the shape of the bounds
    u = np.asarray(u, dtype=np.float64)
    shape = np.broadcast_shapes(u.shape, a.shape)
    u, a, b, flip, p_lo, p_hi = (np.broadcast_to(v, shape) for v in (u, a, b, flip, p_lo, p_hi))
    q = np.where(flip, 1.0 - u, u)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = special.ndtri(p_lo + q * (p_hi - p_lo))
    x = np.where(flip, -x, x)
    far = ~(p_hi > p_lo) | ~np.isfinite(x)
    if np.any(far):
        from scipy import stats

        x = np.array(x, dtype=np.float64, copy=True)
        x[far] = stats.truncnorm.ppf(u[far], a[far], b[far])
    return np.clip(x, a, b)


class PriorError(ValueError):
    """A prior specification in the config is malformed or out of range."""


def _size(size) -> tuple[int, ...]:
    if size is None:
        return ()
    if isinstance(size, (int, np.integer)):
        return (int(size),)
    return tuple(int(s) for s in size)


@dataclass(frozen=True)
class Prior:
    """Base class of the prior families; build instances with :meth:`from_config`."""

    #: Name of the family as written after ``dist:`` in the config.
    dist: ClassVar[str] = ""
    #: Keys required / optional after ``dist`` in the config mapping.
    required: ClassVar[tuple[str, ...]] = ()
    optional: ClassVar[tuple[str, ...]] = ()

    # ------------------------------------------------------------------ construction
    @staticmethod
    def from_config(spec: Any, key: str = "prior") -> Prior:
        """Build a prior from its config mapping (or a bare number = fixed value).

        Parameters
        ----------
        spec : mapping or number
            The config entry, e.g. ``{"dist": "uniform", "low": 0.9, "high": 1.3}``.
        key : str
            Dotted config path of the entry, used in error messages.

        Raises
        ------
        PriorError
            Unknown family, missing or unknown keys, non-finite numbers or bounds that
            leave no probability mass; the message names ``key`` (and the sub-key).
        """
        if isinstance(spec, Prior):
            return spec
        if isinstance(spec, (int, float, np.integer, np.floating)) and not isinstance(spec, bool):
            return Fixed(value=_number(spec, key))
        if not isinstance(spec, Mapping):
            raise PriorError(
                f"config key {key} = {spec!r} is not a prior; expected a number or a mapping "
                f"with 'dist' in {sorted(DISTRIBUTIONS)}"
            )
        dist = spec.get("dist")
        if dist not in DISTRIBUTIONS:
            raise PriorError(
                f"config key {key}.dist = {dist!r} is not a known distribution; allowed: "
                + ", ".join(sorted(DISTRIBUTIONS))
            )
        cls = DISTRIBUTIONS[dist]
        allowed = set(cls.required) | set(cls.optional) | {"dist"}
        unknown = sorted(set(spec) - allowed)
        if unknown:
            raise PriorError(
                f"config key {key} has unknown key(s) {', '.join(unknown)} for dist {dist!r}; "
                f"allowed: {', '.join(sorted(allowed))}"
            )
        missing = [k for k in cls.required if k not in spec]
        if missing:
            raise PriorError(
                f"config key {key} (dist {dist!r}) is missing {', '.join(missing)}; "
                f"required: {', '.join(cls.required)}"
            )
        kwargs = {k: _number(spec[k], f"{key}.{k}") for k in spec if k != "dist"}
        return cls._build(kwargs, key)

    @classmethod
    def _build(cls, kwargs: dict[str, float], key: str) -> Prior:
        raise NotImplementedError

    # ------------------------------------------------------------------ interface
    def sample(self, rng: np.random.Generator, size=None) -> np.ndarray:
        """Draw ``size`` samples (float64 array of that shape) using only ``rng``."""
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        return np.asarray(self._sample(rng, _size(size)), dtype=np.float64)

    def _sample(self, rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
        raise NotImplementedError

    @property
    def support(self) -> tuple[float, float]:
        """Closed interval ``(lo, hi)`` containing every possible sample."""
        raise NotImplementedError

    @property
    def mean(self) -> float:
        """Expectation of the distribution."""
        raise NotImplementedError

    def cdf(self, x) -> np.ndarray:
        """Cumulative distribution function (used by the tests and diagnostics)."""
        raise NotImplementedError

    def to_config(self) -> dict[str, Any]:
        """Config mapping that :meth:`from_config` turns back into this prior."""
        raise NotImplementedError


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise PriorError(f"config key {key} = {value!r} must be a finite number")
    value = float(value)
    if not math.isfinite(value):
        raise PriorError(f"config key {key} = {value!r} must be a finite number")
    return value


def _check_order(low: float, high: float, key: str, strict: bool = True) -> None:
    if (low >= high) if strict else (low > high):
        rel = "<" if strict else "<="
        raise PriorError(f"config key {key}.low = {low!r} must be {rel} {key}.high = {high!r}")


@dataclass(frozen=True)
class Uniform(Prior):
    """Continuous uniform ``U(low, high)``."""

    low: float = 0.0
    high: float = 1.0
    dist: ClassVar[str] = "uniform"
    required: ClassVar[tuple[str, ...]] = ("low", "high")

    @classmethod
    def _build(cls, kw, key):
        _check_order(kw["low"], kw["high"], key)
        return cls(low=kw["low"], high=kw["high"])

    def _sample(self, rng, shape):
        return rng.uniform(self.low, self.high, size=shape)

    @property
    def support(self):
        return (self.low, self.high)

    @property
    def mean(self):
        return 0.5 * (self.low + self.high)

    def cdf(self, x):
        return np.clip((np.asarray(x, float) - self.low) / (self.high - self.low), 0.0, 1.0)

    def to_config(self):
        return {"dist": self.dist, "low": self.low, "high": self.high}


@dataclass(frozen=True)
class Normal(Prior):
    """Normal ``N(mean, std)``, truncated to ``[low, high]`` when bounds are given.

    Truncated draws apply the exact quantile function (:func:`truncated_normal_quantile`)
    to ``rng.random``; there is no rejection loop, so far tails cannot hang.
    """

    loc: float = 0.0
    std: float = 1.0
    low: float = -math.inf
    high: float = math.inf
    dist: ClassVar[str] = "normal"
    required: ClassVar[tuple[str, ...]] = ("mean", "std")
    optional: ClassVar[tuple[str, ...]] = ("low", "high")

    @classmethod
    def _build(cls, kw, key):
        if kw["std"] <= 0:
            raise PriorError(f"config key {key}.std = {kw['std']!r} must be > 0")
        low, high = kw.get("low", -math.inf), kw.get("high", math.inf)
        _check_order(low, high, key)
        a, b = (low - kw["mean"]) / kw["std"], (high - kw["mean"]) / kw["std"]
        # Φ on the side of zero where the interval lies (scipy.stats.norm's sf and cdf)
        mass = special.ndtr(-a) - special.ndtr(-b) if a > 0 else special.ndtr(b) - special.ndtr(a)
        if not mass > 0.0:  # only when the interval lies ~38 std or more away
            raise PriorError(
                f"config key {key}: the bounds [{low!r}, {high!r}] leave no probability mass "
                f"for N({kw['mean']!r}, {kw['std']!r}); put mean within a few std of the interval"
            )
        return cls(loc=kw["mean"], std=kw["std"], low=low, high=high)

    @property
    def truncated(self) -> bool:
        return math.isfinite(self.low) or math.isfinite(self.high)

    @property
    def _ab(self):
        return (self.low - self.loc) / self.std, (self.high - self.loc) / self.std

    def _sample(self, rng, shape):
        if not self.truncated:
            return rng.normal(self.loc, self.std, size=shape)
        a, b = self._ab
        x = self.loc + self.std * truncated_normal_quantile(rng.random(shape), a, b)
        return np.clip(x, self.low, self.high)

    @property
    def support(self):
        return (self.low, self.high)

    @property
    def mean(self):
        if not self.truncated:
            return self.loc
        from scipy import stats

        a, b = self._ab
        return float(stats.truncnorm.mean(a, b, loc=self.loc, scale=self.std))

    def cdf(self, x):
        from scipy import stats

        if not self.truncated:
            return stats.norm.cdf(x, self.loc, self.std)
        a, b = self._ab
        return stats.truncnorm.cdf(x, a, b, loc=self.loc, scale=self.std)

    def to_config(self):
        out = {"dist": self.dist, "mean": self.loc, "std": self.std}
        if math.isfinite(self.low):
            out["low"] = self.low
        if math.isfinite(self.high):
            out["high"] = self.high
        return out


@dataclass(frozen=True)
class UniformInt(Prior):
    """Discrete uniform on the integers ``low, low+1, ..., high`` (both inclusive)."""

    low: int = 0
    high: int = 1
    dist: ClassVar[str] = "uniform_int"
    required: ClassVar[tuple[str, ...]] = ("low", "high")

    @classmethod
    def _build(cls, kw, key):
        for k in ("low", "high"):
            if kw[k] != int(kw[k]):
                raise PriorError(f"config key {key}.{k} = {kw[k]!r} must be an integer")
        _check_order(kw["low"], kw["high"], key, strict=False)
        if kw["low"] < 0:
            raise PriorError(f"config key {key}.low = {kw['low']!r} must be >= 0 (it is a count)")
        return cls(low=int(kw["low"]), high=int(kw["high"]))

    def _sample(self, rng, shape):
        return rng.integers(self.low, self.high, size=shape, endpoint=True)

    @property
    def support(self):
        return (float(self.low), float(self.high))

    @property
    def mean(self):
        return 0.5 * (self.low + self.high)

    def cdf(self, x):
        k = np.floor(np.asarray(x, float))
        return np.clip((k - self.low + 1) / (self.high - self.low + 1), 0.0, 1.0)

    def to_config(self):
        return {"dist": self.dist, "low": self.low, "high": self.high}


@dataclass(frozen=True)
class PowerLaw(Prior):
    """Truncated power law ``p(x) ∝ x^slope`` on ``[low, high]``, ``0 < low < high``.

    With ``slope = -1.9`` this is the subhalo mass function ``dN/dM ∝ M^-1.9``. Sampled
    by the inverse CDF ``x = (low^k + u (high^k - low^k))^(1/k)``, ``k = slope + 1``
    (log-uniform when ``k = 0``).
    """

    slope: float = -1.9
    low: float = 1.0e7
    high: float = 1.0e10
    dist: ClassVar[str] = "power_law"
    required: ClassVar[tuple[str, ...]] = ("slope", "low", "high")

    @classmethod
    def _build(cls, kw, key):
        if kw["low"] <= 0:
            raise PriorError(f"config key {key}.low = {kw['low']!r} must be > 0 for a power law")
        _check_order(kw["low"], kw["high"], key)
        return cls(slope=kw["slope"], low=kw["low"], high=kw["high"])

    @property
    def _k(self) -> float:
        return self.slope + 1.0

    def ppf(self, u) -> np.ndarray:
        """Quantile function (inverse CDF) for ``u`` in [0, 1]."""
        u = np.asarray(u, dtype=np.float64)
        k = self._k
        if abs(k) < 1e-12:
            return self.low * (self.high / self.low) ** u
        # Work relative to ``low`` to keep the powers of 1e7..1e10 well conditioned.
        r = (self.high / self.low) ** k
        return self.low * (1.0 + u * (r - 1.0)) ** (1.0 / k)

    def _sample(self, rng, shape):
        return np.clip(self.ppf(rng.random(shape)), self.low, self.high)

    @property
    def support(self):
        return (self.low, self.high)

    @property
    def mean(self):
        k, lo, hi = self._k, self.low, self.high
        if abs(k) < 1e-12:
            return (hi - lo) / math.log(hi / lo)
        if abs(k + 1.0) < 1e-12:
            return math.log(hi / lo) / (1.0 / lo - 1.0 / hi)
        return k / (k + 1.0) * (hi ** (k + 1) - lo ** (k + 1)) / (hi**k - lo**k)

    def cdf(self, x):
        x = np.clip(np.asarray(x, dtype=np.float64), self.low, self.high)
        k = self._k
        if abs(k) < 1e-12:
            return np.log(x / self.low) / math.log(self.high / self.low)
        return ((x / self.low) ** k - 1.0) / ((self.high / self.low) ** k - 1.0)

    def to_config(self):
        return {"dist": self.dist, "slope": self.slope, "low": self.low, "high": self.high}


@dataclass(frozen=True)
class Fixed(Prior):
    """Degenerate distribution: always ``value``."""

    value: float = 0.0
    dist: ClassVar[str] = "fixed"
    required: ClassVar[tuple[str, ...]] = ("value",)

    @classmethod
    def _build(cls, kw, key):
        return cls(value=kw["value"])

    def _sample(self, rng, shape):
        return np.full(shape, self.value)

    @property
    def support(self):
        return (self.value, self.value)

    @property
    def mean(self):
        return self.value

    def cdf(self, x):
        return (np.asarray(x, float) >= self.value).astype(float)

    def to_config(self):
        return {"dist": self.dist, "value": self.value}


#: Families by their config name.
DISTRIBUTIONS: dict[str, type[Prior]] = {
    cls.dist: cls for cls in (Uniform, Normal, UniformInt, PowerLaw, Fixed)
}


@dataclass(frozen=True)
class JointNormal:
    """A multivariate normal ``N(mean, widen² · cov)`` of named parameters in a box.

    Written in the config as::

        {mean: {a: .., b: ..}, cov: [[..], [..]], widen: 1.5,
         low: {a: .., b: ..}, high: {a: .., b: ..}}

    (``cov`` in the order of ``mean``'s keys). Drawn by the chain rule on the Cholesky
    factor ``L`` of the widened covariance: component ``k`` is
    ``mean_k + Σ_{j<k} L_kj z_j + L_kk z_k``, with ``z_k`` a standard normal truncated
    (:func:`truncated_normal_quantile`) so that component ``k`` lies in its box given the
    earlier ones. Without the box this is exactly the normal; with it, the density in
    the box is the normal's re-weighted by the sequential truncation (not the normal
    conditioned on the box, which needs rejection), which keeps every draw in constant
    time and inside the box.
    """

    names: tuple[str, ...]
    loc: tuple[float, ...]
    cov: tuple[tuple[float, ...], ...]
    widen: float
    low: tuple[float, ...]
    high: tuple[float, ...]

    @staticmethod
    def from_config(spec: Any, key: str = "prior", names=None) -> JointNormal:
        """Build from the config mapping (class docstring); errors name ``key``.
        ``names``: the parameters required, in the order of ``cov`` (default: the order
        of ``mean``'s keys)."""
        allowed = {"mean", "cov", "widen", "low", "high"}
        if not isinstance(spec, Mapping) or set(spec) != allowed:
            have = sorted(spec) if isinstance(spec, Mapping) else spec
            raise PriorError(
                f"config key {key} = {have!r} must be a mapping with exactly the keys "
                f"{', '.join(sorted(allowed))}"
            )
        mean = spec["mean"]
        if not isinstance(mean, Mapping) or not mean:
            raise PriorError(f"config key {key}.mean must map parameter names to numbers")
        if names is None:
            names = tuple(str(k) for k in mean)
        names = tuple(names)
        if set(mean) != set(names):
            raise PriorError(
                f"config key {key}.mean must give exactly {', '.join(names)}, got "
                f"{', '.join(map(str, mean))}"
            )
        loc = tuple(_number(mean[k], f"{key}.mean.{k}") for k in names)
        d = len(names)
        bounds = {}
        for side in ("low", "high"):
            b = spec[side]
            if not isinstance(b, Mapping) or set(b) != set(names):
                raise PriorError(
                    f"config key {key}.{side} must give a number for each of {', '.join(names)}"
                )
            bounds[side] = tuple(_number(b[k], f"{key}.{side}.{k}") for k in names)
        for k, lo, hi, m in zip(names, bounds["low"], bounds["high"], loc, strict=True):
            _check_order(lo, hi, f"{key}.{k}")
            if not lo <= m <= hi:
                raise PriorError(f"config key {key}.mean.{k} = {m!r} must lie in [{lo}, {hi}]")
        cov = spec["cov"]
        rows = cov if isinstance(cov, (list, tuple)) else []
        if len(rows) != d or any(not isinstance(r, (list, tuple)) or len(r) != d for r in rows):
            raise PriorError(f"config key {key}.cov must be a {d} x {d} list of lists")
        c = np.array(
            [
                [_number(v, f"{key}.cov[{i}][{j}]") for j, v in enumerate(r)]
                for i, r in enumerate(rows)
            ]
        )
        if not np.allclose(c, c.T, rtol=1e-9, atol=0.0):
            raise PriorError(f"config key {key}.cov must be symmetric")
        if np.linalg.eigvalsh(c).min() <= 0:
            raise PriorError(f"config key {key}.cov must be positive definite")
        widen = _number(spec["widen"], f"{key}.widen")
        if widen <= 0:
            raise PriorError(f"config key {key}.widen = {widen!r} must be > 0")
        return JointNormal(
            names, loc, tuple(tuple(float(v) for v in r) for r in c), widen, *bounds.values()
        )

    @property
    def cholesky(self) -> np.ndarray:
        """Lower Cholesky factor of ``widen² · cov``."""
        return np.linalg.cholesky(self.widen**2 * np.asarray(self.cov))

    def sample(self, rng: np.random.Generator, size: int) -> dict[str, np.ndarray]:
        """``size`` draws, float64 arrays keyed by name, from ``size × d`` uniforms of
        ``rng`` (one ``rng.random((size, d))`` call)."""
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
        chol = self.cholesky
        u = rng.random((int(size), len(self.names)))
        z = np.zeros_like(u)
        out = np.zeros_like(u)
        for k in range(len(self.names)):
            cond = self.loc[k] + z[:, :k] @ chol[k, :k]
            a = (self.low[k] - cond) / chol[k, k]
            b = (self.high[k] - cond) / chol[k, k]
            z[:, k] = truncated_normal_quantile(u[:, k], a, b)
            out[:, k] = np.clip(cond + chol[k, k] * z[:, k], self.low[k], self.high[k])
        return {name: out[:, k] for k, name in enumerate(self.names)}

    def to_config(self) -> dict[str, Any]:
        """Config mapping that :meth:`from_config` turns back into this prior."""
        return {
            "mean": dict(zip(self.names, self.loc, strict=True)),
            "cov": [list(r) for r in self.cov],
            "widen": self.widen,
            "low": dict(zip(self.names, self.low, strict=True)),
            "high": dict(zip(self.names, self.high, strict=True)),
        }
