"""The spiking model: surrogate spike function, LIF neurons, population encoder and decoder,
the PopSAN actor, and the operation counts of its spikes."""
