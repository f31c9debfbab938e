"""Analysis of trained runs: evaluation episodes and reports, energy, latency, the checkpoint
sweep, training curves and sample efficiency, figures and video."""
