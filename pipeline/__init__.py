"""skinpipe: measured skin diffusion profiles to sum-of-Gaussians fits, USD and renders."""

from __future__ import annotations

__version__ = "0.1.0"
