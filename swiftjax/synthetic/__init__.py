"""A synthetic driving world with a VGGT oracle, for development and benchmarks without weights."""
