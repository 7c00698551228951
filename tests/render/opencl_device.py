"""The OpenCL device the render tests hand to what they call where they do not run on
every device (``cl_device``): the environment's (``$SKINPIPE_OPENCL_DEVICE``, else
auto)."""

from skinpipe.render.device.choice import open_device

DEVICE = open_device()
