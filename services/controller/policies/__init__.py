"""Landing policies: pure objects, heatmap and altitude in, command and status out.

`base` is the contract every policy takes and returns (`Observation`, `Decision`, `Policy`);
`registry` builds a policy by name (`make_policy`, `policy_names`); `config_file` reads a
policy's constants from a user's TOML file; one package per policy (`clearance`, `dovesei`).
"""
