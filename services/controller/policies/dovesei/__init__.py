"""The `dovesei` policy (the DOVESEI 2023 reference lander): `policy` (threshold, lander image, state
machine, `DoveseiPolicy`) and `config` (its constants and their view of the timing presets)."""
