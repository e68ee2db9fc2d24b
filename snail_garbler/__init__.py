"""snail garbler role."""
