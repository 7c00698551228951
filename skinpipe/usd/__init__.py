"""USD assets: skinpipe's schema, guarded stage IO, meshes, the author stage,
validation rules, inspection and shot layers.

Importing this package registers skinpipe's schema plugin with USD: a plugin registered
after the first schema-registry query stays unknown, silently, and every module that
reads or writes skinpipe's prims lives here."""

from .schema import register_schema_plugin

register_schema_plugin()
