"""Controller service: landing policies, the fixed-rate loop, vehicle adapters."""
