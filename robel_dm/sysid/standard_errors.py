"""Standard errors of a least-squares fit to correlated residuals.

`fit.fit` estimates how well the recordings determine each fitted value
from the Jacobian and residuals of its least-squares solution.
"""

from typing import Any

import numpy as np
from scipy import optimize, sparse

# Standard errors. The residuals are not independent: quantized initial
# states and encoder, velocity and current readings leave errors that
# persist for several steps (lag-1 autocorrelation about 0.6 on the virtual
# bus), so the Gauss-Newton covariance s^2 (J^T J)^-1, which counts every
# row as an independent sample, is too small (79% of true errors within 2
# of its standard errors on 5 s D'Claw recordings). The fit uses the
# autocorrelation-consistent sandwich (Newey-West): (J^T J)^-1 S
# (J^T J)^-1, S summing the products of the steps' gradients J_t^T r_t up
# to this far apart with Bartlett weights (1 - lag / (bandwidth + 1)),
# within each episode, and a degrees-of-freedom correction
# (`standard_errors`). Of 0.1, 0.2 and 0.3 s, 0.2 s comes closest to a
# Gaussian's coverage on 5 s recordings (docs/sysid.md).
HAC_BANDWIDTH = 0.2  # s


def _step_gradients(problem, result) -> np.ndarray:
  """Each step's share J_t^T r_t of the cost's gradient, (steps, params)."""
  jacobian = sparse.csr_matrix(result.jac)
  weighted = jacobian.multiply(result.fun[:, None]).tocsr()
  rows = problem.components * problem.joints
  steps = problem.rows // rows
  # Sums each step's rows (angle, velocity, current of every joint).
  summing = sparse.csr_matrix(
    (np.ones(problem.rows), (np.arange(problem.rows) // rows,
                             np.arange(problem.rows))),
    shape=(steps, problem.rows),
  )  # fmt: skip
  return np.asarray((summing @ weighted).todense())


def _hac(gradients: np.ndarray, lengths, bandwidth: int) -> np.ndarray:
  """Newey-West: the covariance of the summed gradients, counting their
  correlation up to `bandwidth` steps apart (Bartlett weights), within
  each episode."""
  meat = np.zeros((gradients.shape[1],) * 2)
  start = 0
  for length in lengths:
    g = gradients[start : start + length]
    start += length
    meat += g.T @ g
    for lag in range(1, min(bandwidth, length - 1) + 1):
      product = g[:-lag].T @ g[lag:]
      meat += (1 - lag / (bandwidth + 1)) * (product + product.T)
  return meat


def standard_errors(
  problem: Any, result: optimize.OptimizeResult
) -> dict[str, np.ndarray]:
  """The standard errors of a fit's values.

  Args:
    problem: the fit's least-squares problem (`fit._Problem`: its
      trajectories, simulator, parameters, residual layout and scaling).
    result: scipy's `least_squares` result of it.

  Returns:
    Absolute standard errors, parameter -> per joint; inf where the
    recordings are too short to estimate one (see HAC_BANDWIDTH).
  """
  jacobian = result.jac
  jacobian = jacobian.toarray() if sparse.issparse(jacobian) else jacobian
  bread = np.linalg.pinv(jacobian.T @ jacobian)
  lengths = [len(t.targets) - 1 for t in problem.trajectories]
  timestep = problem.simulator.substeps * problem.simulator.timestep
  bandwidth = max(1, round(HAC_BANDWIDTH / timestep))
  meat = _hac(_step_gradients(problem, result), lengths, bandwidth)
  variance = np.clip(np.diag(bread @ meat @ bread), 0, None)
  # Degrees of freedom: the Bartlett weights sum to bandwidth + 1 steps, so
  # the steps hold about sum(lengths) / (bandwidth + 1) independent
  # stretches, and the p parameters of a chain were fitted to them; as
  # s^2 divides by n - p, the variance is divided by 1 - p (bandwidth + 1) /
  # sum(lengths). With p (bandwidth + 1) steps or fewer nothing is left to
  # estimate it.
  chains = problem.simulator.chains
  per_chain = np.bincount(chains) * len(problem.parameters)
  fitted_share = (
    per_chain[np.tile(chains, len(problem.parameters))]
    * (bandwidth + 1)
    / sum(lengths)
  )
  with np.errstate(divide='ignore'):
    variance = np.where(fitted_share < 1, variance / (1 - fitted_share), np.inf)
  return problem.values(np.sqrt(variance))
