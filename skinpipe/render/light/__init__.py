"""Light at the surface: ray tracing (Embree), light sampling, the irradiance that
enters each texel with its shadows, and the specular lobe."""
