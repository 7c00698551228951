"""skinpipe: measured skin diffusion profiles to sum-of-Gaussians fits, USD and renders."""

from __future__ import annotations

# Before anything loads pymeshlab (its older TBB) or queries OpenCL platforms: the
# runtimes skinpipe installs are registered with the ICD loader (opencl_runtimes).
from .render import opencl_runtimes  # noqa: F401  (import for its effect)
from .usd.schema import register_schema_plugin

__version__ = "0.1.0"

# Before anything queries USD's schema registry: a plugin registered after that query
# stays unknown, silently.
register_schema_plugin()
