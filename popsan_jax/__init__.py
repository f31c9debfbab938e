"""PopSAN-JAX: population-coded spiking actor networks trained with PPO on MJX tasks."""
