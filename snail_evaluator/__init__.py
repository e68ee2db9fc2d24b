"""snail evaluator role."""
