import numpy as np
import pytest

from StomachUnfoldLib.errors import InputError, SimulationError
from StomachUnfoldLib.newmark import NewmarkBeta, Pull, SpringSystem, simulate, spring_laplacian
from StomachUnfoldLib.params import SolverParameters


def _oscillator(h, t_end=6.0, k=4.0, c=0.4, L=10.0, delta=1.0):
    """Two unit masses on one spring+damper; returns simulated and analytic stretch q(t)."""
    p = SolverParameters(time_step=h, spring_stiffness=k, damping=c, mass_damping=0.0, inner_iterations=3)
    st = NewmarkBeta(np.array([[0, 1]]), np.array([L]), np.ones(2), p)
    x = np.array([[-(L + delta) / 2, 0, 0], [(L + delta) / 2, 0, 0]])
    v = np.zeros_like(x)
    # initial acceleration from the spring force
    f = k * delta
    a = np.array([[f, 0, 0], [-f, 0, 0]])
    n = int(round(t_end / h))
    q = []
    for _ in range(n):
        x, v, a = st.step(x, v, a, np.zeros_like(x))
        q.append(x[1, 0] - x[0, 0] - L)
    t = h * np.arange(1, n + 1)
    mu = 0.5
    w = np.sqrt(k / mu)
    z = c / (2 * np.sqrt(k * mu))
    wd = w * np.sqrt(1 - z * z)
    exact = delta * np.exp(-z * w * t) * (np.cos(wd * t) + z * w / wd * np.sin(wd * t))
    return np.array(q), exact


def test_newmark_matches_damped_two_mass_oscillator():
    q, exact = _oscillator(0.01)
    assert np.max(np.abs(q - exact)) < 2e-3
    # second-order accurate: halving the step divides the error by about 4
    e1 = np.max(np.abs(np.subtract(*_oscillator(0.04))))
    e2 = np.max(np.abs(np.subtract(*_oscillator(0.02))))
    assert 3.0 < e1 / e2 < 5.0


def test_laplacian_rows_sum_to_zero():
    L = spring_laplacian(4, np.array([[0, 1], [1, 2], [2, 3]]), [1.0, 2.0, 3.0]).toarray()
    assert np.allclose(L.sum(1), 0) and L[1, 1] == 3.0


def test_simulation_pulls_a_bar_to_its_targets_and_stops_by_kappa():
    # a chain of 5 vertices; pull the ends apart by 2 mm each: it ends stretched, trace decreasing
    rest = np.stack([np.arange(5.0) * 10, np.zeros(5), np.zeros(5)], 1)
    springs = np.array([[i, i + 1] for i in range(4)])
    targets = rest[[0, 4]] + np.array([[-2.0, 0, 0], [2.0, 0, 0]])
    res = simulate(SpringSystem(rest, springs, np.full(4, 10.0), np.ones(5)), Pull(np.array([0, 4]), targets),
                   SolverParameters(kappa=1e-4, max_iterations=500, unfolding_stiffness=5.0))
    assert res.converged and res.iterations < 500
    assert res.d_trace[-1] < res.d_trace[0]
    assert res.positions[4, 0] - res.positions[0, 0] > 41.0


def test_bad_parameters_and_iteration_cap():
    with pytest.raises(InputError):
        SolverParameters(beta=0.0).validate()
    rest = np.stack([np.arange(3.0) * 10, np.zeros(3), np.zeros(3)], 1)
    res = simulate(SpringSystem(rest, np.array([[0, 1], [1, 2]]), np.full(2, 10.0), np.ones(3)),
                   Pull(np.array([0]), rest[:1] + 50), SolverParameters(kappa=1e-9, max_iterations=3, min_iterations=1))
    assert not res.converged and res.iterations == 3 and res.warnings


def test_divergence_is_detected_and_retried_or_reported():
    rest = np.stack([np.arange(3.0) * 10, np.zeros(3), np.zeros(3)], 1)
    # an explicit-like setting (beta tiny) with a huge step is unstable; the run must not return NaN
    p = SolverParameters(beta=1e-6, gamma=0.5, time_step=50.0, spring_stiffness=50.0, max_retries=1,
                          max_iterations=50, kappa=1e-12)
    try:
        res = simulate(SpringSystem(rest, np.array([[0, 1], [1, 2]]), np.full(2, 10.0), np.ones(3)),
                       Pull(np.array([0]), rest[:1] + 5), p)
        assert np.all(np.isfinite(res.positions))
    except SimulationError as e:
        assert "diverged" in str(e)
