"""The `clearance` policy, by concern: `policy` (the front door, `ClearancePolicy`), `config` (its
constants and presets), `motion` (ego-motion), `ground_map` (the ground map, spots, promise) and
`machine` (one pure step of the phase machine)."""
