"""snail map-owner role."""
