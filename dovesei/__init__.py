"""dovesei: open-vocabulary safe landing for UAVs (CLI and orchestration)."""
