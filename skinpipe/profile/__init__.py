"""Diffusion profiles: the shared types, the radial models, profile files, published
reference data and the sum-of-Gaussians fit."""
