"""skinpipe: measured skin diffusion profiles to sum-of-Gaussians fits, USD and renders."""

from __future__ import annotations

from .usd_schema import register_schema_plugin

__version__ = "0.1.0"

# Before anything queries USD's schema registry: a plugin registered after that query
# stays unknown, silently.
register_schema_plugin()
