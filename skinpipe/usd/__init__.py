"""USD assets: skinpipe's schema, guarded stage IO, meshes, the author stage,
validation rules, inspection and shot layers."""
