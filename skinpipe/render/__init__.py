"""The render stage: scene delegate, texture maps, irradiance, texture-space diffusion
on the OpenCL device, shading and outputs."""
