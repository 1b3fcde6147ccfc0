"""Observation noise distributions of DVBF-LM beyond a plain Gaussian.

* :class:`BeamMixture` -- the classic beam model of a range finder (Thrun et al., *Probabilistic
  Robotics* 6.3): each reading is the emission's noise about the predicted range with
  probability ``1 - eps``, or an outlier uniform over the sensor's range with probability
  ``eps`` (a return from something the map does not hold, a dropout).
* :class:`CircularUniform` -- the uniform density on a circle of circumference ``period``,
  written on the real line (every real number is a point of the circle): the prior of an angle
  known only modulo ``period``.
* :class:`WrappedMixture` -- an angle observed modulo ``period``: Gaussian in the wrapped
  residual with probability ``1 - eps``, uniform over the period otherwise.
"""

from __future__ import annotations

import math

import torch
from pyro.distributions import TorchDistribution, constraints
from torch.distributions.utils import broadcast_all

from ..geometry import wrap_angle


class BeamMixture(TorchDistribution):
    """``(1 - eps) base(x) + eps / outlier_range`` per entry (batch shape that of ``base``).

    Args:
        base: the noise about the predicted reading (e.g. ``Normal(loc, scale)``); its
            ``loc``/``scale``, where it has them, are this distribution's.
        outlier_prob: ``eps`` in ``[0, 1)``, or a tensor broadcasting with the batch (values in
            ``[0, 1]``).
        outlier_range: width of the uniform outlier density (the sensor's range); readings
            are taken to lie in ``[0, outlier_range]``.
    """

    arg_constraints = {}
    support = constraints.real
    has_rsample = False

    def __init__(self, base, outlier_prob, outlier_range: float, validate_args=None):
        if not torch.is_tensor(outlier_prob) and not 0.0 <= outlier_prob < 1.0:
            raise ValueError(f"outlier_prob must be in [0, 1), got {outlier_prob!r}")
        if not outlier_range > 0:
            raise ValueError(f"outlier_range must be positive, got {outlier_range!r}")
        self.base, self.outlier_prob, self.outlier_range = base, outlier_prob, outlier_range
        super().__init__(base.batch_shape, base.event_shape, validate_args=validate_args)

    @property
    def loc(self):
        return self.base.loc

    @property
    def scale(self):
        return self.base.scale

    def expand(self, batch_shape, _instance=None):
        base = self.base.expand(batch_shape)
        # (the outlier probability broadcasts as it is: an expanded copy would send log_prob's
        # elementwise functions down another kernel, which rounds differently)
        return type(self)(base, self.outlier_prob, self.outlier_range, validate_args=False)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        lp = self.base.log_prob(value)
        eps = self.outlier_prob
        if not torch.is_tensor(eps):
            if eps == 0:
                return lp
            eps = lp.new_tensor(eps)
        return torch.logaddexp(lp + torch.log1p(-eps), torch.log(eps / self.outlier_range))

    def sample(self, sample_shape=()):
        x = self.base.sample(sample_shape)
        if not torch.is_tensor(self.outlier_prob) and self.outlier_prob == 0:
            return x
        out = torch.rand(x.shape, dtype=x.dtype) < self.outlier_prob
        return torch.where(out, torch.rand(x.shape, dtype=x.dtype) * self.outlier_range, x)

    @property
    def mean(self):
        eps = self.outlier_prob
        return (1 - eps) * self.base.mean + eps * self.outlier_range / 2


class CircularUniform(TorchDistribution):
    """The uniform density ``1 / period`` on a circle of circumference ``period``, on the real
    line: every real value is a point of the circle, so any unconstrained guide (a Normal about
    an estimate) can be scored against it."""

    arg_constraints = {}
    support = constraints.real
    has_rsample = False

    def __init__(self, period: float, batch_shape=(), validate_args=None):
        self.period = float(period)
        super().__init__(torch.Size(batch_shape), validate_args=validate_args)

    def expand(self, batch_shape, _instance=None):
        return CircularUniform(self.period, batch_shape, validate_args=False)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        return torch.full_like(value, -math.log(self.period))

    def sample(self, sample_shape=()):
        shape = torch.Size(sample_shape) + self.batch_shape
        return torch.rand(shape) * self.period


class WrappedMixture(TorchDistribution):
    """An angle observed modulo ``period``: ``(1 - eps) N(wrap(x - loc); 0, scale) + eps /
    period``, the Gaussian read in the residual wrapped into ``[-period / 2, period / 2)`` (a
    narrow ``scale``, ``<< period``, leaves out the other wraps' negligible mass).

    Args:
        loc, scale: ``[...]`` the Gaussian component's centre and std (rad).
        period: the observation's period (a quarter turn for a Manhattan world's walls).
        outlier_prob: ``eps`` in ``[0, 1)``.
    """

    arg_constraints = {"loc": constraints.real, "scale": constraints.positive}
    support = constraints.real
    has_rsample = False

    def __init__(self, loc, scale, period: float, outlier_prob: float = 0.0, validate_args=None):
        self.loc, self.scale = broadcast_all(loc, scale)
        self.period, self.outlier_prob = float(period), float(outlier_prob)
        super().__init__(self.loc.shape, validate_args=validate_args)

    def expand(self, batch_shape, _instance=None):
        loc, scale = self.loc.expand(batch_shape), self.scale.expand(batch_shape)
        return WrappedMixture(loc, scale, self.period, self.outlier_prob, validate_args=False)

    def residual(self, value: torch.Tensor) -> torch.Tensor:
        """``value - loc`` wrapped into ``[-period / 2, period / 2)``."""
        return wrap_angle(value - self.loc, self.period)

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        r = self.residual(value)
        lp = -0.5 * (r / self.scale) ** 2 - torch.log(self.scale) - 0.5 * math.log(2 * math.pi)
        eps = self.outlier_prob
        if eps == 0:
            return lp
        return torch.logaddexp(lp + math.log1p(-eps), lp.new_tensor(math.log(eps / self.period)))

    def sample(self, sample_shape=()):
        shape = torch.Size(sample_shape) + self.batch_shape
        x = self.loc.expand(shape) + self.scale.expand(shape) * torch.randn(shape)
        if self.outlier_prob:
            out = torch.rand(shape) < self.outlier_prob
            x = torch.where(out, torch.rand(shape) * self.period, x)
        return torch.remainder(x, self.period)
