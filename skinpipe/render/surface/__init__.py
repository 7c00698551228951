"""The skin's surface in texture space: UVs (unwrap, repair, write-back), the texel
maps (position, normal, stretch, regions, coverage) and resampling between the texture
and the image."""
