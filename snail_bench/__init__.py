"""snail-bench: gate counts, compiler and engine throughput, Bristol runs."""
