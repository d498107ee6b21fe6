"""Procedural aerial worlds. `generate` is the front door (the spec, the cache, the pipeline); the
work is done by concern in `classes`, `canvas`, `layout`, `objects`, `blocks`, `parks`, `streets`,
`styles` and `render`."""
