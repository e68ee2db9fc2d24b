"""The native garbling kernel: kernel.c compiled on first use (build.py), plans as checked
kernel programs (program.py), runs driven range by range (run.py)."""
