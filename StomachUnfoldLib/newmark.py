"""Newmark-beta integration of the mass-spring-damper wall model, with the paper's termination rule.

Equation of motion per vertex (LPS mm, unit-free time and mass):
``M a + C v + f_spring(x) = f_unfold(x)`` where each spring pulls with ``k (|l| - L) l/|l|``
(geometrically nonlinear), dampers act on relative velocities of spring ends (``C = c_m M + c L``), and
the unfolding force is ``k_u (g - r)`` on the incision vertices (Eq. 9).

Implicit solve: the spring force splits into a constant linear part and a rotation-dependent part,
``f_spring(x) = L_k x - b(x)`` with ``b(x)`` the springs' rest-length vectors along their current
directions. Newmark-beta (average acceleration by default, beta = 1/4, gamma = 1/2) then asks at every
step for ``A x_{n+1} = rhs + b(x_{n+1})`` with ONE constant sparse matrix
``A = M/(beta h^2) + gamma/(beta h) C + L_k + K_u``: it is factorised once and each step runs a few
local/global fixed-point sweeps (update b, solve) that converge to the fully implicit nonlinear step.
Iteration stops when ``|D(a-1) - D(a)| <= kappa`` (Eq. 11), at the iteration cap, or on divergence
(non-finite or exploding positions), where the step is halved and the run restarted from the last good
state, up to ``max_retries`` times.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import splu

from .errors import SimulationError
from .params import SolverParameters
from .unfolding_force import distance_metric

__all__ = ["SpringSystem", "Pull", "SimulationResult", "spring_laplacian", "spring_rotation_forces",
           "NewmarkBeta", "simulate"]


@dataclass
class SpringSystem:
    """The masses and springs the solver moves: rest positions (LPS mm), springs (S,2), rest lengths (mm), masses.

    A :class:`~StomachUnfoldLib.wall_model.WallModel` has these attributes too and is passed as it is.
    """

    vertices: np.ndarray
    springs: np.ndarray
    rest_length: np.ndarray
    mass: np.ndarray


@dataclass
class Pull:
    """Where the pulled vertices go: ids and destinations (LPS mm); optional plane frame, heights and sides.

    :class:`~StomachUnfoldLib.unfolding_force.UnfoldingTargets` has these attributes too and is passed as it is.
    ``frame`` (3x3, columns v1, v2, n), ``b`` (a point on the plane), ``heights`` (N, mm along n from the
    plane) and ``side`` (+1/-1 per pulled vertex) enable the flattening pull and the guided destinations.
    """

    vertex_ids: np.ndarray
    destinations: np.ndarray
    frame: np.ndarray | None = None
    b: np.ndarray | None = None
    heights: np.ndarray | None = None
    side: np.ndarray | None = None


@dataclass
class SimulationResult:
    """Final positions (LPS mm) and the history of the unfolding run."""

    positions: np.ndarray
    iterations: int
    d_trace: list = field(default_factory=list)
    converged: bool = False
    reason: str = ""
    seconds: float = 0.0
    time_step: float = 1.0
    retries: int = 0
    warnings: list = field(default_factory=list)


def spring_laplacian(n: int, springs: np.ndarray, weights) -> sparse.csr_matrix:
    """Sparse n x n weighted graph Laplacian of the springs: sum_s w_s (e_i - e_j)(e_i - e_j)^T."""
    springs = np.asarray(springs, np.int64)
    w = np.broadcast_to(np.asarray(weights, float), (len(springs),))
    i, j = springs[:, 0], springs[:, 1]
    rows = np.concatenate([i, j, i, j])
    cols = np.concatenate([i, j, j, i])
    vals = np.concatenate([w, w, -w, -w])
    return sparse.csr_matrix((vals, (rows, cols)), shape=(n, n))


def spring_rotation_forces(x: np.ndarray, springs: np.ndarray, kL: np.ndarray) -> np.ndarray:
    """b(x): per vertex sum of ``k L l/|l|`` over its springs (+ on the first end, - on the second), (N,3)."""
    i, j = springs[:, 0], springs[:, 1]
    l = x[i] - x[j]
    norm = np.linalg.norm(l, axis=1)
    f = l * (kL / np.maximum(norm, 1e-9))[:, None]
    n = len(x)
    out = np.empty_like(x)
    for a in range(3):
        out[:, a] = np.bincount(i, f[:, a], minlength=n) - np.bincount(j, f[:, a], minlength=n)
    return out


class NewmarkBeta:
    """Implicit Newmark-beta stepper for a spring network with linear target springs.

    Per axis ``a`` the matrix is ``M/(beta h^2) + gamma/(beta h) C + L_k + diag(stiff[a])`` where
    ``stiff[a]`` holds each vertex's target-spring stiffness along that axis; axes with the same
    stiffness share one factorisation.
    """

    def __init__(self, springs: np.ndarray, rest_length: np.ndarray, mass: np.ndarray,
                 params: SolverParameters, target_stiffness: np.ndarray | None = None,
                 spring_stiffness: np.ndarray | None = None):
        params.validate()
        self.p = params
        self.n = len(mass)
        self.springs = np.asarray(springs, np.int64)
        k = (np.full(len(self.springs), params.spring_stiffness) if spring_stiffness is None
             else np.asarray(spring_stiffness, float))
        self.kL = k * np.asarray(rest_length, float)
        self.mass = np.asarray(mass, float)
        self.Lk = spring_laplacian(self.n, self.springs, k)
        self.M = sparse.diags(self.mass)
        self.C = params.mass_damping * self.M + spring_laplacian(self.n, self.springs, params.damping)
        self.stiff = np.zeros((3, self.n)) if target_stiffness is None else np.asarray(target_stiffness, float)
        self.set_time_step(params.time_step)

    def set_time_step(self, h: float) -> None:
        """(Re)factorise the constant Newmark matrices for time step h (nothing to factorise when explicit)."""
        b, g = self.p.beta, self.p.gamma
        self.h = float(h)
        if self.p.integrator == "explicit":
            self.lu = []
            return
        base = self.M / (b * h * h) + (g / (b * h)) * self.C + self.Lk
        self.lu = []
        for a in range(3):
            for prev in range(a):
                if np.array_equal(self.stiff[prev], self.stiff[a]):
                    self.lu.append(self.lu[prev])
                    break
            else:
                self.lu.append(splu(sparse.csc_matrix(base + sparse.diags(self.stiff[a]))))

    def step_explicit(self, x, v, a, f_target):
        """One semi-implicit (symplectic) Euler step with the same forces; conditionally stable, for comparison."""
        f = (-(self.Lk @ x) + spring_rotation_forces(x, self.springs, self.kL) - self.stiff.T * x + f_target
             - self.C @ v)
        a1 = f / self.mass[:, None]
        v1 = v + self.h * a1
        return x + self.h * v1, v1, a1

    def step(self, x, v, a, f_target):
        """Advance one Newmark-beta step from (x, v, a) under target forces ``stiff * target``; returns (x1, v1, a1)."""
        if self.p.integrator == "explicit":
            return self.step_explicit(x, v, a, f_target)
        b, g, h = self.p.beta, self.p.gamma, self.h
        x_pred = x + h * v + h * h * (0.5 - b) * a
        v_pred = v + h * (1.0 - g) * a
        rhs = (self.M @ x_pred) / (b * h * h) + self.C @ (g / (b * h) * x_pred - v_pred) + f_target
        x1 = x_pred
        for _ in range(self.p.inner_iterations):
            r = rhs + spring_rotation_forces(x1, self.springs, self.kL)
            x1 = np.stack([self.lu[ax].solve(r[:, ax]) for ax in range(3)], axis=1)
        a1 = (x1 - x_pred) / (b * h * h)
        v1 = v_pred + g * h * a1
        return x1, v1, a1


def simulate(system, pull, params: SolverParameters | None = None, progress=None) -> SimulationResult:
    """Run the unfolding: Newmark-beta steps until |D(a-1) - D(a)| <= kappa, the cap, or unrecoverable divergence.

    ``system`` is a SpringSystem (or WallModel), ``pull`` a Pull (or UnfoldingTargets); positions and targets
    are LPS mm. The pulled vertices feel ``unfolding_stiffness * (g - r)``. With the pull's ``frame``, ``b`` and
    ``heights`` every vertex is also pulled along n toward its height with ``flattening_stiffness``, the height
    target moving from the rest height to ``heights`` over the first ``ramp_iterations`` iterations (this keeps
    the matrix constant: the pull acts on one axis of the frame). With the pull's ``side`` (+1/-1 per pulled
    vertex, the side of the base line it goes to) the destinations are guided during the ramp: each moves from
    the vertex's rest position to g along a half-turn about an axis parallel to v1 that passes over the plane
    (+n first), the way a cut edge rotates when a tube is unrolled with its inner surface toward +n; afterwards
    the destinations are the paper's g. ``progress`` (a Progress or callable(fraction)) is called every step.
    If the cap is reached the last state is returned with a warning.
    """
    params = params or SolverParameters()
    return _run(system.vertices, system.springs, system.rest_length, system.mass, pull.vertex_ids,
                pull.destinations, params, progress, getattr(pull, "frame", None), getattr(pull, "b", None),
                getattr(pull, "heights", None), getattr(pull, "side", None))


def _run(rest, springs, rest_length, mass, pulled_ids, targets, params, progress, frame, origin, heights,
         pulled_side) -> SimulationResult:
    flatten_stiffness, ramp_iterations = params.flattening_stiffness, int(params.ramp_iterations)
    t0 = time.perf_counter()
    rest = np.asarray(rest, float)
    pulled_ids = np.asarray(pulled_ids, np.int64)
    targets = np.asarray(targets, float)
    F = np.eye(3) if frame is None else np.asarray(frame, float)
    o = np.zeros(3) if origin is None else np.asarray(origin, float)
    Y0 = (rest - o) @ F
    G = (targets - o) @ F
    n = len(rest)
    stiff = np.zeros((3, n))
    stiff[:, pulled_ids] += params.unfolding_stiffness
    flatten = heights is not None and flatten_stiffness > 0
    guided = pulled_side is not None and ramp_iterations > 0 and len(pulled_ids) > 0
    if guided:
        P0 = Y0[pulled_ids]
        mid = 0.5 * (P0 + G)
        d0 = P0 - mid
        sense = -np.asarray(pulled_side, float)
    if flatten:
        stiff[2] += flatten_stiffness
        h_final = np.asarray(heights, float)
    stepper = NewmarkBeta(springs, rest_length, mass, params, stiff)
    scale = float(np.ptp(Y0, axis=0).max()) + (float(np.abs(G).max()) if len(G) else 0.0)
    retries = 0
    h = params.time_step
    warnings: list[str] = []
    while True:
        y = Y0.copy()
        v = np.zeros_like(y)
        a = np.zeros_like(y)
        trace = [distance_metric(y[pulled_ids], G)]
        converged, reason, diverged = False, "iteration cap", False
        it = 0
        for it in range(1, params.max_iterations + 1):
            s = min(1.0, it / max(ramp_iterations, 1))
            f = np.zeros_like(y)
            if guided and s < 1.0:
                th = sense * np.pi * s
                c, sn = np.cos(th), np.sin(th)
                g_now = np.stack([P0[:, 0] + s * (G[:, 0] - P0[:, 0]),
                                  mid[:, 1] + d0[:, 1] * c - d0[:, 2] * sn,
                                  mid[:, 2] + d0[:, 1] * sn + d0[:, 2] * c], axis=1)
            else:
                g_now = G
            f[pulled_ids] += params.unfolding_stiffness * g_now
            if flatten:
                f[:, 2] += flatten_stiffness * (Y0[:, 2] + s * (h_final - Y0[:, 2]))
            y, v, a = stepper.step(y, v, a, f)
            if not np.all(np.isfinite(y)) or np.abs(y - Y0).max() > 10.0 * scale + 1e3:
                diverged = True
                break
            trace.append(distance_metric(y[pulled_ids], G))
            if progress is not None:
                progress(min(1.0, it / params.max_iterations))
            ramp_done = not (flatten or guided) or it >= ramp_iterations
            if it >= params.min_iterations and ramp_done and abs(trace[-2] - trace[-1]) <= params.kappa:
                converged, reason = True, f"|D(a-1) - D(a)| <= kappa = {params.kappa} mm"
                break
        if not diverged:
            break
        retries += 1
        if retries > params.max_retries:
            raise SimulationError(f"the unfolding simulation diverged at iteration {it} even with time step "
                                  f"{h:g}; lower --time-step or the stiffness, or raise the damping")
        h *= 0.5
        warnings.append(f"simulation diverged at iteration {it}; retried with time step {h:g}")
        stepper.set_time_step(h)
    if not converged:
        warnings.append(f"no convergence within {params.max_iterations} iterations (last |dD| = "
                        f"{abs(trace[-2] - trace[-1]):.3g} mm > kappa); returning the last state")
    return SimulationResult(positions=y @ F.T + o, iterations=it, d_trace=[float(d) for d in trace],
                            converged=converged, reason=reason, seconds=time.perf_counter() - t0,
                            time_step=h, retries=retries, warnings=warnings)
