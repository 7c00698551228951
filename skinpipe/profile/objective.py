"""The fit's objective for one group of curves (one channel of one profile each): eq. 2a
with eq. 2c's r dr weights on the values, plus the radial energy term (the share of
light within each ring's outer edge), both normalised to the data; the Gaussian and
energy bases, and each variance grid's objective with its best weights."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .simplex_weights import gram_weights, simplex_least_squares
from .types import FloatArray


@dataclass
class Curve:
    """One channel of one profile, in the group's scaled units (lengths / L)."""

    rho: FloatArray  # radius / L
    q: FloatArray  # value * L^2 (so that q ~ sum w G(u, rho))
    profile: int
    channel: int
    # The sample weights a = a_scale * a_unit (rho drho / sigma^2, normalised so that the
    # curve's sum a q^2 = 1): the channels of a profile share a_unit (unless weighted by
    # their own standard deviations), so their Gram matrices differ by a factor only.
    a_unit: FloatArray
    a_scale: float
    # The energy term: at the rings' outer edges ``rho_e``, the light within, ``t``, with
    # weights b = b_unit * b_scale (the edges' spacing, shared by a profile's curves;
    # normalised so that the curve's sum b t^2 = energy_weight).
    rho_e: FloatArray
    t: FloatArray
    b_unit: FloatArray
    b_scale: float

    @cached_property
    def a(self) -> FloatArray:
        return self.a_unit * self.a_scale

    @cached_property
    def b(self) -> FloatArray:
        return self.b_unit * self.b_scale


def gaussian_basis(log_u: FloatArray, rho: FloatArray) -> FloatArray:
    """G(u, rho) for a batch of log-variances (..., k) at radii (n,) -> (..., n, k)."""
    u = np.exp(log_u)[..., None, :]
    return np.exp(-(rho[:, None] ** 2) / (2.0 * u)) / (2.0 * np.pi * u)


def energy_basis(log_u: FloatArray, rho: FloatArray) -> FloatArray:
    """The light of G(u) within radius rho, 1 - exp(-rho^2 / 2u), for a batch of
    log-variances (..., k) at radii (n,) -> (..., n, k)."""
    u = np.exp(log_u)[..., None, :]
    return -np.expm1(-(rho[:, None] ** 2) / (2.0 * u))


def grid_fitness(log_u: FloatArray, curves: Sequence[Curve], free_scale: bool) -> tuple[
    FloatArray, FloatArray
]:
    """Objective of each candidate grid (P, k) with its best weights -> (P,), (P, C, k)."""
    n_pop, k = log_u.shape
    hess = np.empty((n_pop, len(curves), k, k))
    grad = np.empty((n_pop, len(curves), k))
    const = np.empty(len(curves))
    basis: dict[int, tuple[FloatArray, FloatArray]] = {}
    gram: dict[tuple[int, int], tuple[FloatArray, FloatArray]] = {}
    for ci, cv in enumerate(curves):
        # Curves of one profile share their radii and, up to a factor, their sample
        # weights: evaluate the Gaussians and their Gram matrices once.
        if id(cv.rho) not in basis:
            basis[id(cv.rho)] = (gaussian_basis(log_u, cv.rho), energy_basis(log_u, cv.rho_e))
        b, e = basis[id(cv.rho)]
        key = (id(cv.a_unit), id(cv.b_unit))
        if key not in gram:
            gram[key] = (np.swapaxes(b * cv.a_unit[:, None], 1, 2) @ b,
                         np.swapaxes(e * cv.b_unit[:, None], 1, 2) @ e)
        unit, edge = gram[key]
        hess[:, ci] = cv.a_scale * unit + cv.b_scale * edge
        grad[:, ci] = np.swapaxes(b, 1, 2) @ (cv.a * cv.q) + np.swapaxes(e, 1, 2) @ (cv.b * cv.t)
        const[ci] = float(np.sum(cv.a * cv.q * cv.q) + np.sum(cv.b * cv.t * cv.t))
    w = gram_weights(hess.reshape(-1, k, k), grad.reshape(-1, k), free_scale)
    w = w.reshape(n_pop, len(curves), k)
    objective = (
        np.einsum("pck,pckl,pcl->p", w, hess, w) - 2.0 * np.einsum("pck,pck->p", w, grad)
        + const.sum()
    )
    return np.maximum(objective, 0.0), w


def objective(log_u: FloatArray, weights: FloatArray, curves: Sequence[Curve]) -> float:
    total = 0.0
    for ci, cv in enumerate(curves):
        resid = cv.q - gaussian_basis(log_u, cv.rho) @ weights[ci]
        edge = cv.t - energy_basis(log_u, cv.rho_e) @ weights[ci]
        total += float(np.sum(cv.a * resid * resid) + np.sum(cv.b * edge * edge))
    return total


def polish_weights(log_u: FloatArray, curves: Sequence[Curve], free_scale: bool) -> FloatArray:
    return np.array([simplex_least_squares(
        np.vstack([gaussian_basis(log_u, cv.rho), energy_basis(log_u, cv.rho_e)]),
        np.concatenate([cv.q, cv.t]), np.concatenate([cv.a, cv.b]), free_scale)
        for cv in curves])
