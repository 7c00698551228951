"""skinpipe: measured skin diffusion profiles to sum-of-Gaussians fits, USD and renders.

Importing the package does nothing else: the USD schema plugin is registered by
``skinpipe.usd`` (before anything of it can query USD's schema registry), and the
OpenCL runtimes by ``skinpipe.render.device`` (before the first platform query)."""

__version__ = "0.1.0"
