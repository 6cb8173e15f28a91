"""The radiance field: methods, fields, samplers, volume rendering, rays, contraction, losses."""
