"""snail client role."""
